"""Misses of the fresh sample of 2026-11-23 evening (seed 11230001): viewer scene centre, bench progress
output, report figure titles, the optics' tiny-field magnification, and training/scoring with the oled
stage off (a bug found on the way), each pinned by what the code is for."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.state import Camera
from controlgs_adapter.viewer.session import scene_centre


def _look_at(eye: tuple[float, float, float], target: tuple[float, float, float], size: int = 12) -> Camera:
    """A pinhole camera at ``eye`` looking at ``target`` (OpenCV axes: x right, y down, z forward)."""
    c, t = torch.tensor(eye, dtype=torch.float64), torch.tensor(target, dtype=torch.float64)
    z = (t - c) / (t - c).norm()
    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    if abs(float(z[1])) > 0.9:
        up = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    x = torch.linalg.cross(up, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    r = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3], w2c[:3, 3] = r, -(r @ c)
    k = torch.tensor([[size, 0.0, size / 2], [0.0, size, size / 2], [0.0, 0.0, 1.0]])
    return Camera(w2c.float(), k, size, size)


def test_scene_centre_is_where_the_axes_meet_and_never_joins_the_poses_graph():
    """Cameras looking at one point: the centre is that point (least squares of the axes, exact here);
    poses that require grad (a camera being optimised) give a plain tensor, the same as detached poses."""
    target = (0.3, -0.2, 0.5)
    cams = [_look_at(e, target) for e in ((0.0, 0.0, -3.0), (3.0, 0.5, 0.0), (-1.0, -2.0, 2.0))]
    live = [Camera(c.world_to_camera.clone().requires_grad_(True), c.intrinsics, c.width, c.height) for c in cams]
    got = scene_centre(live, None)
    assert not got.requires_grad and got.grad_fn is None
    assert got.dtype == torch.float64 and got.shape == (3,)
    assert torch.allclose(got, torch.tensor(target, dtype=torch.float64), atol=1e-5)
    assert torch.equal(got, scene_centre(cams, None))


def test_bench_is_quiet_unless_asked_for_progress(capsys):
    """``run_bench(progress=False)`` (the default, as a library call) writes nothing to stderr or stdout;
    with ``progress=True`` it names its phases on stderr, starting with the phase timings."""
    from controlgs_adapter.benchmarking.accuracy_time import BenchSettings, run_bench

    s = BenchSettings(resolution=16, iterations=1, phase_iterations=1, repeats=1, test_views=1,
                      downsample=(1.0,), power_saving=(0.0,))
    run_bench(s)
    quiet = capsys.readouterr()
    assert (quiet.out, quiet.err) == ("", "")
    run_bench(s, progress=True)
    loud = capsys.readouterr()
    assert loud.out == ""
    assert loud.err.splitlines()[0] == "training phases"


def test_real_magnification_is_the_tiny_field_limit_of_the_chief_ray_height():
    """``real_magnification`` is ``Y / h`` as the field ``h`` goes to 0 (the ratio the bank's chief rays are
    normalised by). Barrel/pincushion distortion makes ``Y / h = m0 + k h^2``; ``m0`` is extrapolated
    here (Richardson) from two small but finite fields, where tracing noise is negligible."""
    import numpy as np

    from controlgs_adapter.downstream.optics.prescription import Prescription
    from controlgs_adapter.downstream.optics.raytrace import chief_ray, real_magnification

    rx = Prescription.cardboard()
    h = np.array([1e-3, 2e-3])
    for lam in (486.0, 550.0, 656.0):
        _, y, ok = chief_ray(rx, lam, h)
        assert ok.all()
        f1, f2 = y / h
        m0 = (4.0 * f1 - f2) / 3.0
        assert abs(f2 - f1) > 1e-10 * abs(m0)  # the distortion term is really there at these fields
        assert real_magnification(rx, lam) == pytest.approx(m0, rel=6e-12, abs=0)


def _runs(mask) -> list[tuple[int, int]]:
    """``[start, stop)`` of each run of True in a 1-D boolean array."""
    out, start = [], None
    for i, v in enumerate(list(mask) + [False]):
        if v and start is None:
            start = i
        elif not v and start is not None:
            out.append((start, i))
            start = None
    return out


def test_comparison_figure_titles_fit_over_their_panels(tmp_path):
    """Fig. 1's panel titles (the rows :func:`evaluation.side_by_side` gives, two-line settings, metrics)
    are set small enough to sit over their own image: in the written PNG, every dark title pixel lies within the columns of the
    image panel below it, never over the gap or a neighbour's panel."""
    from matplotlib.image import imread

    from controlgs_adapter.report import plot_comparison

    img = torch.full((3, 32, 32), 0.5)
    rows = {m: [(img, img, 31.25, 0.912), (img, img, 28.5, 0.88)] for m in ("no_ss", "ss", "controlgs")}
    path = plot_comparison({"gt": img, "settings": [(2.0, 0.4), (1.0, 0.0)], "rows": rows}, tmp_path / "fig.png")
    px = torch.from_numpy(imread(str(path))[..., :3].copy()).double()
    grey = ((px - 0.5).abs() < 0.02).all(-1)
    dark = px.max(-1).values < 0.35
    panel_rows = _runs((grey.sum(1) > 0.2 * grey.sum(1).max()).tolist())
    assert len(panel_rows) == 1 + len(rows)
    top = 0
    for y0, y1 in panel_rows:
        cols = _runs((grey[y0:y1].sum(0) > 0.5 * (y1 - y0)).tolist())
        assert len(cols) in (1, 4)  # the ground truth alone, then rendered/eye for two settings
        ys, xs = torch.nonzero(dark[top:y0], as_tuple=True)
        assert len(xs) > 50, "no title above the panels"
        for x0, x1 in cols:
            near = (xs >= x0 - 10) & (xs < x1 + 10)
            assert near.any(), "a panel without a title"
        inside = torch.zeros_like(xs, dtype=torch.bool)
        for x0, x1 in cols:
            inside |= (xs >= x0) & (xs < x1)
        assert inside.all(), f"title pixels outside their panel at x={sorted(set(xs[~inside].tolist()))[:5]}"
        top = y1


def test_training_with_oled_off_scores_the_display_pixels_as_boxes_at_full_size(tiny):
    """With the ``oled`` stage off the eye image stays at the display size S/d; the trainer compares it with
    the ground truth as box pixels at S (how the viewer shows and scores it), so a run with oled off
    trains exactly like one with oled on when nothing follows the oled stage (it is that box emission).
    It used to stop with a ShapeError at the first sample with d > 1."""
    from controlgs_adapter.training import TrainConfig, Trainer

    scene, model = tiny
    losses = []
    for oled in (True, False):
        t = Trainer(model, scene.views("train"), TrainConfig(iterations=4, seed=3, checkpoint_every=0, max_downsample=4.0),
                    effects={"resample": True, "display": True, "oled": oled})
        try:
            losses += [t.step() for _ in range(4)]
        finally:
            t.cgs.unwrap()
    on, off = losses[:4], losses[4:]
    assert all(math.isfinite(v) for v in on)
    assert off == pytest.approx(on, rel=1e-6, abs=0)


def test_evaluation_scores_an_oled_off_eye_image_as_box_pixels_at_full_size():
    """The grid's scores of a pipeline without the ``oled`` stage (eye image at S/d) are those of the same
    pipeline with it (box emission to S is all that stage does), at every d; they used to stop with a
    ShapeError for d > 1."""
    from controlgs_adapter.evaluation import make_pipeline, scores
    from controlgs_adapter.state import RuntimeState

    g = torch.Generator().manual_seed(5)
    gt = torch.rand(3, 24, 24, generator=g)
    image = (gt + 0.1 * torch.randn(3, 24, 24, generator=g)).clamp(0, 1)
    on = make_pipeline({"resample": True, "display": True, "oled": True}).eval()
    off = make_pipeline({"resample": True, "display": True, "oled": False}).eval()
    for d, rho in ((1.0, 0.0), (2.0, 0.4), (3.0, 0.0)):
        state = RuntimeState(downsample=d, power_saving=rho)
        with torch.no_grad():
            e_on, e_off = on(image, state, reference=gt), off(image, state, reference=gt)
        assert e_off.shape[-1] == round(24 / d)
        want, got = scores(e_on, gt, {}), scores(e_off, gt, {})
        assert got == pytest.approx(want, rel=1e-6, abs=0)
        assert math.isfinite(got["psnr"]) and 0 < got["ssim"] < 1
