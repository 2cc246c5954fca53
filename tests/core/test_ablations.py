"""Tests of ``controlgs_adapter.ablations``: the ablation table (stages kept, state-blind or not) is the
paper's Tbl. 4."""

from __future__ import annotations

from controlgs_adapter.ablations import ABLATIONS


def test_ablations_table_is_the_papers():
    assert ABLATIONS == {"wo_lens": (("resample", "display"), False), "wo_display": (("lens", "resample"), False),
                         "wo_resample": (("lens", "display"), False),
                         "state_blind": (("lens", "resample", "display"), True)}
