"""Misses of the fresh sample of 2026-11-23 evening (seed 11230001), each pinned by what the code is for."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.models.train_backbone import train_reference_model
from controlgs_adapter.downstream.lens import LUTMap
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.scene import load_builtin_scene
from controlgs_adapter.state import Camera
from controlgs_adapter.training import TrainConfig, Trainer
from controlgs_adapter.viewer.session import orbit_camera


def _look_at(eye: tuple[float, float, float], size: int = 12) -> Camera:
    """A pinhole camera at ``eye`` looking at the origin (OpenCV axes: x right, y down, z forward)."""
    c = torch.tensor(eye, dtype=torch.float32)
    z = -c / c.norm()
    up = torch.tensor([0.0, 1.0, 0.0]) if abs(float(z[1])) < 0.9 else torch.tensor([1.0, 0.0, 0.0])
    x = torch.linalg.cross(up, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    r = torch.stack([x, y, z])
    w2c = torch.eye(4)
    w2c[:3, :3], w2c[:3, 3] = r, -(r @ c)
    k = torch.tensor([[size, 0.0, size / 2], [0.0, size, size / 2], [0.0, 0.0, 1.0]])
    return Camera(w2c, k, size, size)


def test_reference_trainer_follows_its_seed_not_the_global_generator():
    """Two fits with the same ``seed`` are the same model to the bit, whatever the global generator
    holds (the view order of every epoch is drawn from the seeded generator), and the global generator is
    left as it was."""
    cams = [_look_at((0.0, 0.0, -3.0)), _look_at((3.0, 0.0, 0.0)), _look_at((0.0, -3.0, 0.5))]
    g = torch.Generator().manual_seed(0)
    images = torch.rand(3, 3, 12, 12, generator=g)
    pts = torch.rand(30, 3, generator=g) - 0.5
    kw = dict(iterations=9, feat_dim=4, n_offsets=2, max_anchors=12, progress=False, seed=5)
    fits = []
    for global_seed in (1, 2):
        torch.manual_seed(global_seed)
        before = torch.get_rng_state()
        fits.append(dict(train_reference_model(images, cams, pts, **kw).state_dict()))
        assert torch.equal(torch.get_rng_state(), before)  # the caller's generator is left as it was
    a, b = fits
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_lut_map_refuses_a_grid_that_is_not_finite():
    """A LUT grid holding NaN or inf is refused, naming ``grid`` (it would sample NaN everywhere it reaches)."""
    grid = torch.rand(3, 4, 5, 2)
    LUTMap(grid)  # finite: accepted
    for bad in (math.nan, math.inf):
        g = grid.clone()
        g[1, 2, 3, 0] = bad
        with pytest.raises(InputValueError, match="grid"):
            LUTMap(g)


def test_orbit_camera_never_attaches_the_camera_to_its_inputs_graph():
    """Orbiting is a viewer move: a centre or camera pose that requires grad gives a camera whose pose does
    not (and the same pose as from detached inputs)."""
    cam = _look_at((0.0, 0.0, -3.0))
    centre = torch.tensor([0.1, -0.2, 0.3], requires_grad=True)
    w2c = cam.world_to_camera.clone().requires_grad_(True)
    live = Camera(w2c, cam.intrinsics, cam.width, cam.height)
    out = orbit_camera(live, centre, 30.0, -10.0)
    want = orbit_camera(cam, centre.detach(), 30.0, -10.0)
    assert not out.world_to_camera.requires_grad
    assert torch.equal(out.world_to_camera, want.world_to_camera)


def test_a_trainer_starts_in_its_first_iterations_optics_mode():
    """Before any step the pipeline's optics stage is in iteration 0's mode (``distortion`` while
    ``psf_fraction`` leaves iterations to it), and the switch to ``psf_mode`` comes at its iteration."""
    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    torch.manual_seed(0)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=5)
    effects = {"lens": True, "resample": True, "display": True, "oled": True, "optics": {"mode": "distortion"}}
    config = TrainConfig(iterations=2, checkpoint_every=0, psf_fraction=0.5, psf_mode="exact")
    t = Trainer(model.eval(), scene.views("train"), config, effects=effects)
    try:
        assert [t.optics_mode(i) for i in (0, 1)] == ["distortion", "exact"]
        assert t.pipeline["optics"].mode == "distortion"
        t.step()
        assert t.pipeline["optics"].mode == "distortion"
        t.step()
        assert t.pipeline["optics"].mode == "exact"
    finally:
        t.cgs.unwrap()


def test_optics_bench_reports_the_one_minute_load_average(monkeypatch, capsys):
    """The bench's header gives the machine's 1-minute load average (what competes with the timings now)."""
    import os

    from controlgs_adapter.downstream.optics import bench

    monkeypatch.setattr(os, "getloadavg", lambda: (1.3, 5.5, 15.75))
    rows = bench.run(sizes=["16"], repeat=1, scaling=False, radiometries=bench.RADIOMETRIES[:1], threads=1)
    assert rows
    header = capsys.readouterr().out.splitlines()[0]
    assert "load average 1.3," in header and "1 threads" in header


def test_from_points_with_colours_starts_features_small_and_random():
    """With colours and no fitting steps, the features are the documented small random start: normal with
    standard deviation 0.1 (checked on 4000 values), drawn from ``seed``."""
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(500, 3, generator=g, dtype=torch.float64)
    cols = torch.rand(500, 3, generator=g, dtype=torch.float64)
    m = NeuralGaussianModel.from_points(pts, cols, feat_dim=8, n_offsets=2, voxel_size=1e-3, color_fit_steps=0, seed=4)
    f = m._anchor_feat.detach().double().flatten()
    assert f.numel() == 4000
    assert abs(float(f.mean())) < 0.01 and 0.095 < float(f.std()) < 0.105 and float(f.abs().max()) < 0.6
    again = NeuralGaussianModel.from_points(pts, cols, feat_dim=8, n_offsets=2, voxel_size=1e-3, color_fit_steps=0, seed=4)
    assert torch.equal(again._anchor_feat, m._anchor_feat)


def test_optics_bench_page_names_the_command_line_it_was_given(tmp_path):
    """Called from Python (``cli.main(argv)``) as from a shell, the written page names the exact command
    line, quoted for a shell, so that it can be re-run."""
    import shlex

    from controlgs_adapter.cli import main

    out = tmp_path / "a dir"
    argv = ["optics", "bench", "--sizes", "16", "--radiometry", "radiance", "--repeat", "1", "--no-scaling",
            "--threads", "1", "--out", str(out)]
    assert main(argv) == 0
    page = (out / "optics_bench.md").read_text()
    command = page.split("Command: `", 1)[1].split("`", 1)[0]
    assert shlex.split(command) == ["controlgs", *argv]


def test_viewer_rotation_is_exact_in_float64():
    """The viewer's Rodrigues rotation keeps its axis' float64: about z it is the closed form to 1e-15, and
    about a skew axis orthonormal to 1e-14 with the axis fixed (float32 would leave ~1e-8 errors)."""
    from controlgs_adapter.viewer.session import _rotation

    t = math.radians(37.0)
    want = torch.tensor([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]],
                        dtype=torch.float64)
    r = _rotation(torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64), 37.0)
    assert r.dtype == torch.float64 and torch.allclose(r, want, rtol=0, atol=1e-15)
    axis = torch.tensor([0.3, -0.7, 0.64], dtype=torch.float64)
    r = _rotation(axis, 123.4)
    assert torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-14)
    assert torch.allclose(r @ axis, axis, rtol=0, atol=1e-14)


def test_image_loss_module_names_pred_and_target_in_its_call_order():
    """``ImageLoss()(pred, target)``: a shape mismatch names ``pred``'s shape first, as the call gave them."""
    from controlgs_adapter.errors import ShapeError
    from controlgs_adapter.losses import ImageLoss

    with pytest.raises(ShapeError, match=r"pred and target must have the same shape, got \[3, 16, 16\] and \[3, 12, 12\]"):
        ImageLoss()(torch.rand(3, 16, 16), torch.rand(3, 12, 12))


def test_condition_response_figure_has_a_column_for_the_longest_strip(tmp_path):
    """Strips of unequal length: the figure has as many columns as the longest (2 in by 120 dpi each), the
    shorter row's missing panels left blank."""
    import struct

    pytest.importorskip("matplotlib")
    from controlgs_adapter.report import plot_condition_response

    img = torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(0))
    strips = {"resample": [("d=1", img), ("d=2", img)], "display": [("p=0", img), ("p=0.3", img), ("p=0.6", img)]}
    path = plot_condition_response(strips, tmp_path / "response.png")
    width, height = struct.unpack(">II", path.read_bytes()[16:24])  # the PNG's IHDR
    assert (width, height) == (round(2.0 * 3 * 120), round(2.1 * 2 * 120))


def test_optics_bench_page_names_sys_argv_when_main_is_given_none(tmp_path, monkeypatch):
    """As the console script calls it (``main()``), the page names the shell's arguments after the
    program name: ``sys.argv[1:]``."""
    import shlex

    from controlgs_adapter.cli import main

    out = tmp_path / "b"
    argv = ["optics", "bench", "--sizes", "16", "--radiometry", "radiance", "--repeat", "1", "--no-scaling",
            "--threads", "1", "--out", str(out)]
    monkeypatch.setattr("sys.argv", ["/some/bin/controlgs", *argv])
    assert main() == 0
    page = (out / "optics_bench.md").read_text()
    command = page.split("Command: `", 1)[1].split("`", 1)[0]
    assert shlex.split(command) == ["controlgs", *argv]
