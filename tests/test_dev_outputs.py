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
    from controlgs_adapter.commands.demo import DEMO_ITERATIONS
    from controlgs_adapter.training import TrainConfig

    base = TrainConfig()
    for cmd in ("demo", "train"):
        args = build_parser().parse_args([cmd])
        assert args.iterations == DEMO_ITERATIONS  # the one documented exception: a CPU-sized demo
        assert (args.checkpoint_every, args.lr, args.cond_dim, args.psf_fraction) == (
            base.checkpoint_every, base.lr, base.cond_dim, base.psf_fraction)
