"""Mutation sweep 5, batch 1: behaviours that a plausible one-line bug changed and no test observed (the
pre-warp fit's continuation beyond the frame, the display LUT's evaluation cache, the float64 oracle's
dtype on an empty scene, the barrier of a distributed context's normal exit, the exit status of
``controlgs scene build-backbone``). See docs/testing.md."""

from __future__ import annotations

import json
import time

import pytest
import torch

from _two_ranks import peer_rank

from controlgs_adapter import plugins

D = torch.float64
needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")


# ----------------------------------------------------------------------------- pre-warp fit beyond the frame
@needs_optics
def test_fit_continues_the_measured_residual_beyond_the_psf_centroids_where_the_frame_cuts_the_light():
    """``fit_bank_prewarp`` (module docstring of prewarp_fit): where a display pixel's light leaves the eye
    frame its centroid cannot be measured, and the map there is the chief ray plus the bank PSF's own
    centroid offset plus the *measured* discretisation residual (map - chief - PSF centroid on the measured
    pixels) continued outwards. At 8 px the measured pixels are the inner 6 x 6 (36 / 64, pinned in
    test_sweep_downstream_pipeline); the outer ring must be that continuation, not the chief ray minus the
    offset (which lands up to 0.03 px off at 8 px)."""
    from controlgs_adapter.downstream.lens import chief_ray_grid, pixel_grid
    from controlgs_adapter.downstream.optics.stage import PSFOptics
    from controlgs_adapter.downstream.prewarp_fit import _fill_invalid, _psf_centroids, fit_bank_prewarp

    optics = PSFOptics()
    bank = optics.bank
    lut = fit_bank_prewarp(optics, 8, modes=("exact",), pool=1, gain_iterations=0)
    assert lut.meta["residuals"]["exact"]["measured_fraction"] == 36 / 64
    p = pixel_grid((8, 8), D)
    target = lut.displacement_exact.double() + p  # eye position of every display pixel
    chief, _ = chief_ray_grid(bank.chief.double(), (8, 8), sample_x=bank.chief_x, sample_y=bank.chief_y)
    offset = _psf_centroids(bank, p, D)  # the PSFs' first moments (brute-forced in test_sweep_downstream_pipeline)
    assert float(offset[:, 0].abs().max()) * 4 > 1e-3  # the edge pixels' PSFs are off-centre (px at 8 px)
    residual = target - chief - offset
    inner = torch.zeros(3, 8, 8, dtype=torch.bool)
    inner[:, 1:-1, 1:-1] = True
    expected = _fill_invalid(torch.where(inner[..., None], residual, torch.zeros_like(residual)), inner)
    assert float((residual - expected).abs().max()) * 4 < 1e-5  # px at 8 px (float32 tables)


# ----------------------------------------------------------------------------- DisplayLUTMap evaluation cache
def test_display_lut_map_evaluates_once_per_size_and_again_after_the_table_changes():
    """``DisplayLUTMap`` (class docstring): the grid and gain are evaluated once per (size, dtype, device,
    table) and returned again as they are; another size, or an in-place change of the table, evaluates
    anew (the change is seen)."""
    from controlgs_adapter.downstream.lens import DisplayLUTMap

    g = torch.Generator().manual_seed(3)
    disp = 0.01 * torch.randn(3, 4, 4, 2, generator=g)
    lut = DisplayLUTMap({"exact": (disp, 1.0 + 0.1 * torch.rand(3, 4, 4, generator=g))}, (10.0, 10.0), "stretch")
    grid1, gain1 = lut((6, 6), D, "cpu")
    grid2, gain2 = lut((6, 6), D, "cpu")
    assert grid2 is grid1 and gain2 is gain1
    other, _ = lut((5, 6), D, "cpu")
    assert other is not grid1 and other.shape == (3, 5, 6, 2)
    before = lut((6, 6), D, "cpu")[0].clone()
    with torch.no_grad():
        lut.displacement_exact += 0.05  # the eye position moves by 0.05 (display-normalised, stretch: grid too)
    after, _ = lut((6, 6), D, "cpu")
    torch.testing.assert_close(after, before + 0.05, rtol=0, atol=1e-6)


# ----------------------------------------------------------------------------- float64 oracle, empty scene
def test_reference_splatter_returns_float64_for_an_empty_scene():
    """``rasterize_reference`` "Returns float64 tensors" (its docstring), also with no Gaussian at all (no
    splat promotes an accumulator): colour the background, alpha and depth zero, all float64."""
    from controlgs_adapter.rendering.splatter_reference import rasterize_reference
    from controlgs_adapter.state import Camera

    cam = Camera(torch.eye(4, dtype=D), torch.tensor([[8.0, 0, 2], [0, 8.0, 1.5], [0, 0, 1]], dtype=D), 4, 3)
    empty = [torch.zeros(0, *s) for s in ((3,), (3,), (4,), (), (3,))]
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = rasterize_reference(*empty, cam, bg)
    assert (out.color.dtype, out.alpha.dtype, out.depth.dtype) == (D, D, D)
    assert torch.equal(out.color, bg.to(D)[:, None, None].expand(3, 3, 4))
    assert torch.equal(out.alpha, torch.zeros(1, 3, 4, dtype=D)) and torch.equal(out.depth, torch.zeros(1, 3, 4, dtype=D))
    assert out.visible.shape == (0,)


# ----------------------------------------------------------------------------- distributed: a normal exit waits
_LATE_RANK1 = """
import os, sys, time
from controlgs_adapter.distributed import init_distributed
os.environ.update({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": sys.argv[1]})
with init_distributed("gloo", timeout=60.0) as ctx:
    ctx.barrier()
    time.sleep(0.6)
"""


def test_leaving_a_dist_context_normally_waits_for_every_rank(monkeypatch):
    """``DistContext.close`` / ``__exit__`` (docs: "after a barrier, so that no rank tears its connections
    down while a peer still uses them"): on a normal exit rank 0 waits for rank 1, which leaves 0.6 s
    later, so rank 0's exit takes about 0.6 s, not an instant."""
    from controlgs_adapter.distributed import init_distributed

    with peer_rank(monkeypatch, _LATE_RANK1):
        with init_distributed("gloo", timeout=60.0) as ctx:
            ctx.barrier()
            start = time.perf_counter()
        waited = time.perf_counter() - start
    assert waited >= 0.5, f"rank 0 left after {waited:.3f} s without waiting for rank 1"


# ----------------------------------------------------------------------------- controlgs scene build-backbone
def test_scene_build_backbone_exits_zero_and_writes_the_backbone(tmp_path, monkeypatch, capsys):
    """``controlgs scene build-backbone`` (docs/demo.md) bakes the backbone into ``--out`` and, having done
    so, exits with status 0 (a script or CI job checks it), with the settings given in build.json."""
    from controlgs_adapter.cli import main

    out = tmp_path / "bb"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    rc = main(["scene", "build-backbone", "--resolution", "16", "--iterations", "1", "--max-anchors", "20",
               "--n-offsets", "2", "--out", str(out)])
    assert rc == 0
    assert f"backbone written to {out}" in capsys.readouterr().out
    info = json.loads((out / "build.json").read_text())
    assert (info["variant"], info["resolution"], info["iterations"], info["n_offsets"]) == ("ar", 16, 1, 2)
    assert 0 < info["anchors"] <= 20
