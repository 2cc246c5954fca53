"""Demo and development tools never write into the installed package nor into ./docs unless asked."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from controlgs_adapter.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]


def test_bench_writes_docs_only_with_doc() -> None:
    parser = build_parser()
    assert parser.parse_args(["bench"]).out is None
    assert parser.parse_args(["bench", "--doc"]).out == Path("docs") / "benchmarks.md"
    assert parser.parse_args(["optics", "bench"]).out is None
    assert parser.parse_args(["optics", "bench", "--doc"]).out == Path("docs")


def test_build_backbone_needs_an_explicit_folder(capsys) -> None:
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(["scene", "build-backbone"])
    assert e.value.code == 2 and "--out" in capsys.readouterr().err


@pytest.mark.parametrize("script", sorted(p.name for p in (ROOT / "benchmarks").glob("*.py")))
def test_benchmark_scripts_default_to_printing(script: str) -> None:
    text = (ROOT / "benchmarks" / script).read_text()
    defaults = re.findall(r"add_argument\([^)]*default=([^,)]*)", text)
    assert not [d for d in defaults if "docs" in d], f"{script}: a default path into docs/"


def test_cli_training_defaults_come_from_train_config() -> None:
    import inspect
    from dataclasses import replace

    from controlgs_adapter.ablations import ABLATIONS
    from controlgs_adapter.commands.adapters import DEMO_ITERATIONS, train_config
    from controlgs_adapter.distributed import init_distributed
    from controlgs_adapter.training import TrainConfig

    base = replace(TrainConfig(), iterations=DEMO_ITERATIONS)  # the one documented exception: a CPU-sized demo
    for cmd in ("demo", "train"):
        args = build_parser().parse_args([cmd])
        assert train_config(args, "controlgs") == base, cmd
        for name, (modules, blind) in ABLATIONS.items():
            assert train_config(args, name) == replace(base, modules=modules, state_blind=blind), (cmd, name)
    args = build_parser().parse_args(["train"])
    defaults = inspect.signature(init_distributed).parameters
    assert (args.dist_timeout, args.exchange) == (defaults["timeout"].default, defaults["exchange"].default)


def test_cli_training_options_reach_train_config() -> None:
    from dataclasses import replace

    from controlgs_adapter.commands.adapters import train_config
    from controlgs_adapter.training import TrainConfig

    args = build_parser().parse_args(["train", "--iterations", "7", "--lr", "0.02", "--cond-dim", "3", "--psf-fraction",
                                      "0.25", "--optics", "exact", "--checkpoint-every", "2", "--seed", "5",
                                      "--batch-size", "4"])
    want = TrainConfig(iterations=7, lr=0.02, cond_dim=3, psf_fraction=0.25, psf_mode="exact", checkpoint_every=2,
                       seed=5, batch_size=4)
    assert train_config(args, "controlgs") == want
    assert train_config(args, "controlgs", seed=9) == replace(want, seed=9)
