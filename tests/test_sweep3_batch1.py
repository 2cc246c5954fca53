"""Misses of the fresh sample of 2026-11-23 evening (seed 11230001): Octree-GS's anchor opacity, ControlGS's
target records, the heatmap's cell labels, ``controlgs bench``'s command line and ``fit_prewarp``'s default
length, each pinned by what the code is for."""

from __future__ import annotations

import dataclasses
import inspect
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torch import nn

from controlgs_adapter import ControlGS
from controlgs_adapter.evaluation import GridResult
from controlgs_adapter.report import plot_heatmaps

from scaffold_standin import ScaffoldStandIn

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------ Octree-GS anchor opacity
def _octree(opacity: torch.Tensor | None, a: int = 6, k: int = 2, f: int = 4):
    from controlgs_adapter.backends.octree_gs import OctreeGSModel

    g = torch.Generator().manual_seed(3)
    return OctreeGSModel(
        anchor=torch.randn(a, 3, generator=g), offset=torch.zeros(a, k, 3), anchor_feat=torch.randn(a, f, generator=g),
        scaling=torch.full((a, 6), -2.0), level=torch.randint(0, 3, (a, 1), generator=g), extra_level=torch.zeros(a),
        mlp_opacity=nn.Sequential(nn.Linear(f + 3, k), nn.Tanh()), mlp_cov=nn.Sequential(nn.Linear(f + 3, 7 * k)),
        mlp_color=nn.Sequential(nn.Linear(f + 3, 3 * k), nn.Sigmoid()), voxel_size=0.1, standard_dist=3.0,
        opacity=opacity)


def test_octree_model_without_file_opacity_keeps_octree_gs_anchor_opacity_layout():
    """Octree-GS keeps one opacity per anchor (``_opacity [A, 1]``, class docstring); a model built without one
    (a ``point_cloud.ply`` with no ``opacity`` column) has the same layout, so parameters move between the two."""
    given = torch.linspace(-1.0, 1.0, 6)[:, None]
    with_file = _octree(given)
    without = _octree(None)
    assert without._opacity.shape == with_file._opacity.shape == (6, 1)
    without.load_state_dict(with_file.state_dict())  # strict: every tensor of one fits the other
    assert torch.equal(without._opacity, given)


# ------------------------------------------------------------------------------ ControlGS targets
def test_wrapped_targets_are_read_only_hashable_records():
    """``cgs.targets`` records what the wrapper attached to (``unwrap`` finds its hooks by them): a Target
    cannot be edited afterwards, and as a value it hashes like its equal."""
    cgs = ControlGS.wrap(ScaffoldStandIn(5, seed=1))
    try:
        first = cgs.targets[0]
        with pytest.raises(dataclasses.FrozenInstanceError):
            first.fc1 = "mlp_cov.0"  # type: ignore[misc]
        assert first.fc1 == "mlp_opacity.0"
        copy = dataclasses.replace(first)
        assert copy == first and hash(copy) == hash(first)
        assert len(set(cgs.targets)) == 3 and {first: "x"}[copy] == "x"
    finally:
        model = cgs.unwrap()
    assert all(not getattr(model, d)[0]._forward_hooks for d in ("mlp_opacity", "mlp_cov", "mlp_color"))


# ------------------------------------------------------------------------------ heatmap labels
def _heatmap_pixels(tmp_path: Path, d: int, p: int, cell: tuple[int, int], value: float, name: str):
    """The heatmap (ControlGS minus SS-backbone, PSNR) of a d x p grid: one cell of +10 dB sets the colour
    range, ``cell`` is +``value``, the rest 0."""
    import matplotlib.image

    delta = torch.zeros(d, p, 1, dtype=torch.float64)
    delta[d - 1, 0, 0] = 10.0
    delta[cell[0], cell[1], 0] = value
    ss = torch.full((d, p, 1), 20.0, dtype=torch.float64)
    r = GridResult(tuple(float(2 ** i) for i in range(d)), tuple(0.2 * j for j in range(p)),
                   {"ss": {"psnr": ss}, "controlgs": {"psnr": ss + delta}})
    return torch.from_numpy(matplotlib.image.imread(plot_heatmaps(r, tmp_path / name)))


@pytest.mark.parametrize("d, p", [(2, 3), (3, 2)])
def test_every_heatmap_cell_carries_its_value(tmp_path, d, p):
    """Every cell of the grid is labelled with its difference, for grids wider than tall and taller than wide:
    +0.01 and +0.04 dB against a +/-10 dB range get the same colour, so only the label tells them apart."""
    for cell in ((0, p - 1), (d - 1, p - 1), (0, 0)):
        a = _heatmap_pixels(tmp_path, d, p, cell, 0.01, "a.png")
        b = _heatmap_pixels(tmp_path, d, p, cell, 0.04, "b.png")
        assert a.shape == b.shape and not torch.equal(a, b), cell


# ------------------------------------------------------------------------------ controlgs bench
@pytest.mark.slow
def test_bench_report_names_the_command_line_it_was_run_with(tmp_path):
    """``docs/benchmarks.md`` starts with how it was generated: the report names ``controlgs bench`` with the
    options given, quoted so that a shell runs the same command again."""
    out = tmp_path / "my report.md"
    args = ["bench", "--quick", "--resolution", "16", "--iterations", "2", "--test-views", "1", "--no-progress",
            "--out", str(out)]
    p = subprocess.run([sys.executable, "-c", "import sys; from controlgs_adapter.cli import main; sys.exit(main())",
                        *args], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    text = out.read_text()
    assert text in p.stdout  # printed too
    m = re.search(r"Generated by `([^`]*)`", text)
    assert m is not None, text[:500]
    assert shlex.split(m.group(1)) == ["controlgs", *args], m.group(1)


# ------------------------------------------------------------------------------ fit_prewarp
def test_fit_prewarp_default_length_is_the_documented_recipe():
    """docs/pipeline.md documents ``fit_prewarp(..., steps=10_000, lr=1e-3)``, the paper's recipe (Supp. B.1);
    the function's defaults are those (10,000 steps take minutes here, so read, not run)."""
    from controlgs_adapter.downstream.prewarp_fit import fit_prewarp

    doc = (ROOT / "docs" / "pipeline.md").read_text()
    m = re.search(r"fit_prewarp\(pipeline, images, targets, steps=([0-9_]+), lr=([0-9.e-]+)\)", doc)
    assert m is not None
    params = inspect.signature(fit_prewarp).parameters
    assert params["steps"].default == int(m.group(1)) == 10_000
    assert params["lr"].default == float(m.group(2)) == 1e-3
