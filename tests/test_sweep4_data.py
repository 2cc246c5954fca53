"""Mutation audit of the dataset readers and the display path's colour / power stages (sweep 4):
each test pins a behaviour that a plausible one-line bug would change and no other test observed,
against a by-hand computation, an independent implementation (Pillow, numpy) or the documented rule."""

from __future__ import annotations


import numpy as np
import pytest
import torch
from PIL import Image

from controlgs_adapter.datasets import (Frame, PosedImages, SceneData, area_resize, check_scene, read_blender,
                                       read_colmap, read_instant_ngp, undistort_points,
                                       working_size)
from controlgs_adapter.downstream.display import (PANEL_COEFFICIENTS, display_mapping, display_mapping_with_stats,
                                                  display_power)
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera

W, H, F = 8, 6, 10.0
#: OpenCV camera at the origin looking down +z, and one turned round (looking down -z)
FRONT = torch.eye(4)
BACK = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))


def _camera(w2c: torch.Tensor = FRONT, w: int = W, h: int = H, f: float = F) -> Camera:
    k = torch.tensor([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    return Camera(w2c.clone(), k, w, h)


def _scene(poses: list[torch.Tensor], *, source: str = "mem") -> SceneData:
    frames = [Frame(f"v{i:02d}", _camera(p), torch.zeros(3, H, W)) for i, p in enumerate(poses)]
    return SceneData({"train": frames, "test": []}, source=source, format="builtin")


# ---------------------------------------------------------------------------------------------
# check_scene (datasets/sanity.py)


def test_check_scene_counts_points_left_of_or_above_the_image_as_outside():
    """A point in front of the camera but projecting to u < 0 (or v < 0) is not "inside the image":
    by hand with f = 10, c = (4, 3): (0, 0, 1) -> (4, 3) inside, (-1, 0, 1) -> u = -6, (0, -1, 1) -> v = -7."""
    pts = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 1.0], [0.0, -1.0, 1.0]])
    report = check_scene(_scene([FRONT]), pts, min_in_front=0.0)
    assert report["in_front"] == {"v00": pytest.approx(1 / 3)}


def test_check_scene_refuses_non_finite_points():
    pts = torch.tensor([[0.0, 0.0, 1.0], [float("nan"), 0.0, 1.0]])
    with pytest.raises(InputValueError, match="points contains 1 non-finite"):
        check_scene(_scene([FRONT]), pts)


def test_check_scene_with_no_points_reports_no_fractions():
    """``in_front`` is documented empty without points; an empty ``[0, 3]`` tensor is no points."""
    report = check_scene(_scene([FRONT, BACK]), torch.zeros(0, 3))
    assert report["in_front"] == {} and report["blind"] == [] and report["points"] == 0


def test_check_scene_projects_an_even_stride_of_at_most_20000_points():
    """sanity.py's ``_MAX_POINTS`` doc comment: at most 20,000 points per camera, an even stride
    through the given ones; 20,001 points take every 2nd (10,001), and the fraction is that of those."""
    n = 20_001
    pts = torch.zeros(n, 3)
    pts[:, 2] = 1.0
    pts[1::2, 0] = -1.0          # every odd point projects left of the image; the stride keeps only even ones
    report = check_scene(_scene([FRONT]), pts)
    assert report["points"] == len(range(0, n, 2)) == 10_001
    assert report["in_front"]["v00"] == 1.0


def _blind_warning(n_seeing: int, n_blind: int) -> str:
    data = _scene([FRONT] * n_seeing + [BACK] * n_blind)
    pts = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.1, 2.0]])
    with pytest.warns(RuntimeWarning) as rec:
        check_scene(data, pts)
    return str(rec[0].message)


def test_check_scene_warning_names_up_to_five_blind_cameras_and_marks_more():
    """Five blind cameras are all named with nothing after them; a sixth is left out as ", ..."."""
    msg = _blind_warning(6, 5)
    assert msg.endswith(": v06, v07, v08, v09, v10")
    msg = _blind_warning(7, 6)
    assert msg.endswith(": v07, v08, v09, v10, v11, ...")


def test_check_scene_counts_points_in_the_camera_plane_as_behind():
    """Depth 0 is not in front (Camera.project: "Depth <= 0 is behind"): points in the plane of every
    camera make all of them blind and the message reports 100 % behind."""
    pts = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(InputValueError, match=r"on average 100% lie behind the cameras"):
        check_scene(_scene([FRONT, FRONT]), pts)


# ---------------------------------------------------------------------------------------------
# working size, area resize, the decoded-image cache (datasets/base.py)


def test_working_size_keeps_at_least_one_pixel_on_the_short_side():
    """Docstring: "never upscaled; at least 1 pixel": 1 x 100 at a longer side of 2 is 1 x 2 (1/50 rounds to 0)."""
    assert working_size(1, 100, resolution=2) == (1, 2)
    assert working_size(100, 1, resolution=2) == (2, 1)
    assert working_size(1, 9, factor=4.0) == (1, 2)


def test_area_resize_by_a_non_integer_factor_matches_pillows_bilinear_reduce():
    """Non-integer factors use antialiased bilinear, i.e. the filter Pillow's BILINEAR resize applies
    when reducing (an independent implementation); plain bilinear would alias."""
    rng = np.random.default_rng(0)
    img = rng.uniform(size=(2, 11, 17)).astype(np.float32)
    out = area_resize(torch.from_numpy(img), 4, 6)
    ref = np.stack([np.asarray(Image.fromarray(c, "F").resize((6, 4), Image.BILINEAR)) for c in img])
    assert out.shape == (2, 4, 6)
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-5)


def test_area_resize_returns_the_input_when_the_size_already_matches():
    """Docstring: "Returns the input if the size already matches"."""
    x = torch.rand(3, 5, 7)
    assert area_resize(x, 5, 7) is x


def test_scene_data_default_background_is_black_and_loaded_images_carry_no_graph():
    """SceneData.background (``[3]``, "the model's background") defaults to black; an RGBA
    pixel of alpha 0.25 over it keeps a quarter of its colour. A background that requires grad is a
    constant of the loaded images (no graph reaches them)."""
    rgba = torch.zeros(4, H, W, dtype=torch.float64)
    rgba[:3], rgba[3] = 0.8, 0.25
    data = SceneData({"train": [Frame("a", _camera(), rgba)]})
    assert torch.equal(data.background, torch.zeros(3))
    img = data.views("train").image(0)
    torch.testing.assert_close(img, torch.full((3, H, W), 0.2))
    bg = torch.tensor([1.0, 0.0, 0.5], requires_grad=True)
    img = PosedImages(data.splits["train"], background=bg).image(0)
    assert not img.requires_grad
    torch.testing.assert_close(img, (0.2 + 0.75 * bg.detach())[:, None, None].expand(3, H, W))


def test_cache_holds_an_image_exactly_the_size_of_its_budget():
    """``cache_bytes`` is the budget "of at most": an image of exactly that many bytes is kept."""
    frames = [Frame("a", _camera(), torch.rand(3, H, W, dtype=torch.float64))]
    size = 3 * H * W * 4                                     # float32 [3, H, W]
    views = PosedImages(frames, cache_bytes=size)
    assert views.image(0) is views.image(0)
    views = PosedImages(frames, cache_bytes=size - 1)
    first, second = views.image(0), views.image(0)
    assert first is not second and torch.equal(first, second)


# ---------------------------------------------------------------------------------------------
# NeRF-synthetic reader (datasets/blender.py)


def _tiny_blender(root) -> None:
    from _datasets_synth import ring_poses, write_json, write_png

    c2w = ring_poses(1)[0]
    write_png(root / "train" / "r_0.png", np.zeros((H, W, 4), dtype=np.uint8))
    write_json(root / "transforms_train.json",
               {"camera_angle_x": 0.8, "frames": [{"file_path": "./train/r_0", "transform_matrix": c2w.tolist()}]})


def test_read_blender_records_the_folder_it_read(tmp_path):
    """SceneData.source: "what was read (a path ...), for messages and report headers"."""
    _tiny_blender(tmp_path)
    data = read_blender(tmp_path)
    assert data.source == str(tmp_path) and data.points is None



# ---------------------------------------------------------------------------------------------
# display mapping (downstream/display.py)


def _analytic_dimming_gradient(x: torch.Tensor, target: float) -> torch.Tensor:
    """d/dx of sum(x * target / P(x)) by hand, for x > 0 with nothing clipped: P(x) = sum_c w_c mean(x_c),
    so d/dx_j = target / P - target * sum(x) / P^2 * w_c(j) / (H W)."""
    w = torch.tensor(PANEL_COEFFICIENTS, dtype=torch.float64)
    hw = x.shape[-1] * x.shape[-2]
    p = float((x.mean(dim=(-2, -1)) * w).sum())
    s = float(x.sum())
    return target / p - target * s / p**2 * (w / hw)[:, None, None].expand_as(x)


def test_dimming_gradient_by_hand_with_and_without_a_reference():
    """Module docstring: "Gradients flow through P(image); the reference is a constant". Without a
    reference P_ref = P(image) taken as a constant too, so the gradient is not simply (1 - rho)."""
    x = (torch.rand(3, 3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.5 + 0.2)
    x.requires_grad_(True)
    rho = 0.4
    p = float(display_power(x.detach()))
    (g,) = torch.autograd.grad(display_mapping(x, rho).sum(), x)
    torch.testing.assert_close(g, _analytic_dimming_gradient(x.detach(), (1 - rho) * p))
    ref = torch.full((3, 2, 2), 0.3, dtype=torch.float64)
    (g,) = torch.autograd.grad(display_mapping(x, rho, ref).sum(), x)
    torch.testing.assert_close(g, _analytic_dimming_gradient(x.detach(), (1 - rho) * float(display_power(ref))))


def test_no_gradient_reaches_the_reference_or_its_power():
    """The reference (or a given reference_power) is a constant of the mapping: no gradient reaches it."""
    x = torch.full((3, 2, 2), 0.3, dtype=torch.float64, requires_grad=True)
    ref = torch.full((3, 2, 2), 0.2, dtype=torch.float64, requires_grad=True)
    g = torch.autograd.grad(display_mapping(x, 0.2, ref).sum(), [x, ref], allow_unused=True)
    assert g[0] is not None and g[1] is None
    p_ref = display_power(ref.detach()).requires_grad_(True)
    g = torch.autograd.grad(display_mapping(x, 0.2, reference_power=p_ref).sum(), [x, p_ref], allow_unused=True)
    assert g[0] is not None and g[1] is None


def test_pixels_exactly_at_the_display_range_ends_are_not_clipped():
    """``clipped_fraction`` counts values outside [0, 1]: an image of exact 0s and 1s mapped at scale 1
    (rho = 0, P_ref = its own power) clips nothing."""
    x = torch.zeros(3, 2, 2, dtype=torch.float64)
    x[:, 0] = 1.0
    out, stats = display_mapping_with_stats(x, 0.0, reference_power=display_power(x))
    assert float(stats["scale"]) == 1.0 and torch.equal(out, x)
    assert float(stats["clipped_fraction"]) == 0.0
    x[0, 1, 1] = 1.5                      # one value of 12 above the range
    x[1, 1, 0] = -0.5                     # one below
    _, stats = display_mapping_with_stats(x, 0.0, reference_power=display_power(x))
    assert float(stats["clipped_fraction"]) == pytest.approx(2 / 12)


def test_read_blender_background_must_be_a_finite_srgb_colour_and_is_kept_as_a_constant(tmp_path):
    """Docstring: ``background`` is an sRGB colour in [0, 1] (checked finite); a negative component is
    refused even when another is positive. The colour kept is detached (no graph through the data)."""
    _tiny_blender(tmp_path)
    with pytest.raises(InputValueError, match="background"):
        read_blender(tmp_path, background=torch.tensor([float("nan"), 0.0, 0.0]))
    with pytest.raises(InputValueError, match=r"background must be an sRGB colour in \[0, 1\]"):
        read_blender(tmp_path, background=torch.tensor([-0.25, 0.5, 0.5]))
    bg = torch.tensor([0.25, 0.5, 0.75], requires_grad=True)
    kept = read_blender(tmp_path, background=bg).background
    assert not kept.requires_grad and kept.tolist() == [0.25, 0.5, 0.75]


# ---------------------------------------------------------------------------------------------
# instant-ngp reader (datasets/instant_ngp.py)


def _tiny_ngp(root, frame_extra: dict | None = None, missing: int = 0, n: int = 3, size=(W, H), **top) -> None:
    """``n`` frames with images, then ``missing`` frames whose image is not there."""
    from _datasets_synth import ring_poses, write_json, write_png

    frames = []
    for i, c2w in enumerate(ring_poses(n + missing)):
        if i < n:
            write_png(root / "images" / f"f{i}.png", np.zeros((size[1], size[0], 3), dtype=np.uint8))
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": c2w.tolist(), **(frame_extra or {})})
    write_json(root / "transforms.json", {"fl_x": 9.0, "fl_y": 9.0, "w": size[0], "h": size[1], **top, "frames": frames})


def test_read_instant_ngp_defaults_to_a_black_background_and_records_the_folder(tmp_path):
    """Docstring: ``background`` "(default black)"; SceneData.source is what was read."""
    _tiny_ngp(tmp_path)
    data = read_instant_ngp(tmp_path)
    assert torch.equal(data.background, torch.zeros(3))
    assert data.source == str(tmp_path) and data.points is None


# ---------------------------------------------------------------------------------------------
# COLMAP reader (datasets/colmap.py)


def _colmap_text_scene(root, points: list[tuple[tuple[float, float, float], int]] | None = None):
    """One PINHOLE camera and one image as text files; ``points``: ``(xyz, track length)`` written as a
    binary points3D.bin by hand from COLMAP's documented layout (u64 count; per point: u64 id, 3 f64
    xyz, 3 u8 rgb, f64 error, u64 track length, then (u32 image id, u32 point2D index) per element)."""
    import struct

    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"# cameras\n1 PINHOLE {W} {H} 10 10 4 3\n")
    (sparse / "images.txt").write_text("# images\n1 1 0 0 0 0 0 0 1 a.png\n\n")
    (root / "images").mkdir()
    Image.fromarray(np.zeros((H, W, 3), dtype=np.uint8)).save(root / "images" / "a.png")
    if points is not None:
        raw = struct.pack("<Q", len(points))
        for pid, (xyz, track) in enumerate(points):
            raw += struct.pack("<Q3d3BdQ", pid + 1, *xyz, 10, 20, 30, 0.5, track)
            raw += b"".join(struct.pack("<II", 1, j) for j in range(track))
        (sparse / "points3D.bin").write_bytes(raw)
    return root


def test_colmap_points_file_whose_last_point_has_an_empty_track_reads(tmp_path):
    """A point observed by no image (track length 0) is still a valid record, also as the file's last."""
    pts = [((1.0, 2.0, 3.0), 2), ((-4.0, 5.5, 0.25), 0)]
    data = read_colmap(_colmap_text_scene(tmp_path, pts), holdout=0)
    assert data.points.tolist() == [[1.0, 2.0, 3.0], [-4.0, 5.5, 0.25]]


def test_colmap_points_file_with_a_single_point(tmp_path):
    data = read_colmap(_colmap_text_scene(tmp_path, [((0.5, -1.5, 2.0), 1)]), holdout=0)
    assert data.points.tolist() == [[0.5, -1.5, 2.0]]


def test_read_instant_ngp_warning_names_five_missing_images_then_marks_more(tmp_path):
    """Docstring: missing images are skipped "with a RuntimeWarning naming how many and the first few"
    (five: ``_NAMED``'s doc comment)."""
    _tiny_ngp(tmp_path / "five", missing=5)
    with pytest.warns(RuntimeWarning) as rec:
        read_instant_ngp(tmp_path / "five")
    assert str(rec[0].message).endswith("5 of 8 frames list an image that is not there, skipped: "
                                        "images/f3.png, images/f4.png, images/f5.png, images/f6.png, images/f7.png")
    _tiny_ngp(tmp_path / "six", missing=6)
    with pytest.warns(RuntimeWarning) as rec:
        read_instant_ngp(tmp_path / "six")
    assert str(rec[0].message).endswith("skipped: images/f3.png, images/f4.png, images/f5.png, images/f6.png, "
                                        "images/f7.png, ...")


def test_read_instant_ngp_holds_out_every_8th_frame_by_default(tmp_path):
    """Signature default ``holdout=8`` (3DGS's ``--eval`` llffhold, docs: every holdout-th by name is a
    test view): of 10 frames f0..f9, f0 and f8 are test views."""
    _tiny_ngp(tmp_path, n=10)
    data = read_instant_ngp(tmp_path)
    assert [f.name for f in data.splits["test"]] == ["images/f0.png", "images/f8.png"]
    assert len(data.splits["train"]) == 8


@pytest.mark.parametrize("key", ["fl_x", "fl_y"])
def test_read_instant_ngp_refuses_a_zero_focal_length_naming_the_keys(tmp_path, key):
    """A focal length of 0 is not usable (the message asks for fl_x / fl_y > 0)."""
    _tiny_ngp(tmp_path, **{key: 0.0})
    with pytest.raises(FileFormatError, match=r"no usable focal length \(give fl_x / fl_y > 0"):
        read_instant_ngp(tmp_path)


def test_read_instant_ngp_takes_a_one_pixel_image(tmp_path):
    """``w, h`` must be > 0: a 1 x 1 capture (w = h = 1) is a valid camera."""
    _tiny_ngp(tmp_path, size=(1, 1), cx=0.5, cy=0.5, fl_x=0.75, fl_y=0.5)   # focal lengths > 0, below 1 px
    cam = read_instant_ngp(tmp_path, holdout=0).splits["train"][0].camera
    assert (cam.width, cam.height) == (1, 1)
    assert cam.intrinsics.tolist() == [[0.75, 0.0, 0.5], [0.0, 0.5, 0.5], [0.0, 0.0, 1.0]]


def test_identity_mapping_stats_are_detached():
    """display_mapping_with_stats: the stats are "each [...], detached", also on the rho = 0 shortcut."""
    x = torch.full((3, 2, 2), 0.5, dtype=torch.float64, requires_grad=True)
    out, stats = display_mapping_with_stats(x, 0.0)
    assert out is x
    assert not any(v.requires_grad for v in stats.values())
    assert float(stats["power"]) == pytest.approx(0.5 * sum(PANEL_COEFFICIENTS))


# ---------------------------------------------------------------------------------------------
# undistortion (datasets/images.py)


def test_undistort_points_converges_like_newtons_method():
    """Docstring: the inverse is found "by Newton's method": quadratic convergence, so 4 iterations from
    the distorted position already land on the pinhole position to float64 precision (a wrong Jacobian
    term still converges, but only linearly: ~1e-5 px off after 4 steps). Forward model in numpy from
    the module docstring's formula."""
    k1, k2, p1, p2, k3 = d = (-0.2, 0.05, 0.02, -0.015, 0.01)
    g = np.linspace(-0.6, 0.6, 7)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    fx, fy, cx, cy = 100.0, 90.0, 40.5, 30.25
    k = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    distorted = torch.from_numpy(np.stack([fx * xd + cx, fy * yd + cy], axis=-1))
    expected = np.stack([fx * x + cx, fy * y + cy], axis=-1)
    got = undistort_points(distorted, k, d, iterations=4).numpy()
    assert np.abs(got - expected).max() < 1e-9


def test_clipped_fraction_is_per_image_of_a_batch():
    """Stats are "each [...]": a batch of two images gets one clipped fraction each (by hand: the first
    has 1 of 12 values above 1 at scale 1, the second none)."""
    x = torch.full((2, 3, 2, 2), 0.5, dtype=torch.float64)
    x[0, 0, 0, 0] = 1.5
    _, stats = display_mapping_with_stats(x, 0.0, reference_power=display_power(x))
    assert stats["clipped_fraction"].tolist() == [pytest.approx(1 / 12), 0.0]
