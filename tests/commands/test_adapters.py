"""Tests of ``controlgs_adapter.commands.adapters``: ``--effects`` parsing, the ``TrainConfig`` of each adapter and
ablation built from the command-line options, and ``train_adapters`` resuming a run's checkpoints."""

from __future__ import annotations

import inspect
from dataclasses import replace
from typing import Any

import pytest

from controlgs_adapter.ablations import ABLATIONS
from controlgs_adapter.cli import build_parser
from controlgs_adapter.commands.adapters import DEMO_ITERATIONS, effects_from, train_adapters, train_config
from controlgs_adapter.distributed import init_distributed
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.training import DEFAULT_EFFECTS, TrainConfig


def test_effects_from_keeps_pipeline_order() -> None:
    """Names in any order, spaces and empty items ignored, come back in pipeline order, all on; None is the
    default effects (a copy); an empty or unknown list is refused."""
    names = list(DEFAULT_EFFECTS)
    got = effects_from(f" {names[-1]} ,{names[0]},")
    assert list(got) == [names[0], names[-1]] and all(v is True for v in got.values())
    assert effects_from([names[-1], names[0]]) == got
    assert effects_from(f" {names[0]} ,, ") == {names[0]: True}
    assert effects_from(None) == dict(DEFAULT_EFFECTS) and effects_from(None) is not DEFAULT_EFFECTS
    assert "foveation" not in DEFAULT_EFFECTS and list(effects_from(f"{names[0]},foveation")) == ["foveation", names[0]]
    for bad in ("", " , ", "nope", f"{names[0]},bloom", []):
        with pytest.raises(InputValueError, match="^--effects must be a comma-separated list of"):
            effects_from(bad)  # type: ignore[arg-type]


def test_training_defaults_come_from_train_config() -> None:
    """``demo`` and ``train`` train TrainConfig's defaults except the CPU-sized iterations; each ablation drops
    one module and stays state-aware, only ``state_blind`` is blind (paper Tbl. 4); the distributed options'
    defaults are init_distributed's."""
    assert DEMO_ITERATIONS == 1000
    base = replace(TrainConfig(), iterations=DEMO_ITERATIONS)
    for cmd in ("demo", "train"):
        args = build_parser().parse_args([cmd])
        assert train_config(args, "controlgs") == base, cmd
        assert (train_config(args, "controlgs").modules, train_config(args, "controlgs").batch_size) == (None, 1)
        for name, (modules, blind) in ABLATIONS.items():
            assert train_config(args, name) == replace(base, modules=modules, state_blind=blind), (cmd, name)
    want = {"wo_lens": (("resample", "display"), False), "wo_display": (("lens", "resample"), False),
            "wo_resample": (("lens", "display"), False), "state_blind": (("lens", "resample", "display"), True)}
    args = build_parser().parse_args(["train"])
    for name, (modules, blind) in want.items():
        c = train_config(args, name)
        assert (c.modules, c.state_blind) == (modules, blind), name
    defaults = inspect.signature(init_distributed).parameters
    assert (args.dist_timeout, args.exchange) == (defaults["timeout"].default, defaults["exchange"].default)


def test_training_options_reach_train_config() -> None:
    args = build_parser().parse_args(["train", "--iterations", "7", "--lr", "0.02", "--cond-dim", "3", "--psf-fraction",
                                      "0.25", "--optics", "exact", "--checkpoint-every", "2", "--seed", "5",
                                      "--batch-size", "4", "--lens-conditioning", "xy", "--gaze-jitter-deg", "1.5"])
    want = TrainConfig(iterations=7, lr=0.02, cond_dim=3, psf_fraction=0.25, psf_mode="exact", checkpoint_every=2,
                       seed=5, batch_size=4, lens_conditioning="xy", gaze_jitter_deg=1.5)
    assert train_config(args, "controlgs") == want
    assert train_config(args, "controlgs", seed=9) == replace(want, seed=9)
    assert train_config(args, "controlgs", seed=0).seed == 0
    assert train_config(args, "wo_lens") == replace(want, modules=("resample", "display"))


def test_train_adapters_resume_messages(tiny: Any, tmp_path: Any, capsys: pytest.CaptureFixture[str]) -> None:
    """A fresh run says nothing about resuming, a second run of the same length says where it resumes (and
    nothing else), a shorter one also says that it keeps what was trained; ``trained`` receives the iterations
    actually trained."""
    scene, model = tiny
    views = scene.views("train")

    def args(iterations: int) -> Any:
        return build_parser().parse_args(["train", "--iterations", str(iterations), "--checkpoint-every", "1",
                                          "--effects", "display", "--no-progress", "--cond-dim", "2"])

    trained: dict[str, int] = {}
    paths = train_adapters(views, model, tmp_path, args(2), ["controlgs"], trained=trained)
    assert paths == {"controlgs": tmp_path / "controlgs.controlgs.safetensors"} and paths["controlgs"].is_file()
    assert trained == {"controlgs": 2} and capsys.readouterr().out == ""
    train_adapters(views, model, tmp_path, args(2), ["controlgs"], trained=trained)
    assert capsys.readouterr().out.splitlines() == ["controlgs: resuming at iteration 2"]
    train_adapters(views, model, tmp_path, args(1), ["controlgs"], trained=trained)
    assert capsys.readouterr().out.splitlines() == [
        "controlgs: resuming at iteration 2",
        "controlgs: the checkpoint is already at iteration 2 > --iterations 1; keeping what was trained"]
    assert trained == {"controlgs": 2}
