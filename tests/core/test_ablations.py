"""Tests of ``controlgs_adapter.ablations``: the ablation table (stages kept, state-blind or not) is the
paper's Tbl. 4 plus w/o foveation, trained among all ablations only with the foveation effect."""

from __future__ import annotations

import argparse

from controlgs_adapter.ablations import ABLATIONS, ablations_for
from controlgs_adapter.training import DEFAULT_EFFECTS, TrainConfig, modules_for


def test_ablations_table_is_the_papers():
    assert ABLATIONS == {"wo_lens": (("resample", "display"), False), "wo_display": (("lens", "resample"), False),
                         "wo_resample": (("lens", "display"), False),
                         "state_blind": (("lens", "resample", "display"), True),
                         "wo_foveation": (("lens", "resample", "display"), False)}


def test_wo_foveation_is_trained_only_with_the_foveation_effect_and_lacks_its_module():
    from controlgs_adapter.commands.adapters import train_config

    paper = ("wo_lens", "wo_display", "wo_resample", "state_blind")
    assert ablations_for(DEFAULT_EFFECTS) == paper
    assert ablations_for([*DEFAULT_EFFECTS, "foveation"]) == (*paper, "wo_foveation")
    base = TrainConfig()
    args = argparse.Namespace(iterations=2, lr=base.lr, cond_dim=2, psf_fraction=base.psf_fraction, optics="fast",
                              checkpoint_every=0, seed=0, effects="lens,resample,display,oled,foveation")
    full = modules_for({"lens": True, "resample": True, "display": True, "oled": True, "foveation": True})
    assert "foveation" in full and train_config(args, "controlgs").modules is None  # the effects' modules: with it
    ablated = train_config(args, "wo_foveation")
    assert ablated.modules == tuple(m for m in full if m != "foveation") and not ablated.state_blind
