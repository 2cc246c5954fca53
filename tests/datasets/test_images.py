"""Tests of ``controlgs_adapter.datasets.images``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from controlgs_adapter.datasets import read_colmap, undistort_points
from controlgs_adapter.datasets.base import Frame
from controlgs_adapter.datasets.images import distort_normalized, image_size, load_frame_image, read_image, undistort
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera


def _cam(w: int, h: int, fx: float = 10.0, fy: float = 12.0, cx: float | None = None, cy: float | None = None) -> Camera:
    k = torch.tensor([[fx, 0.0, w / 2.0 if cx is None else cx], [0.0, fy, h / 2.0 if cy is None else cy], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), k, w, h)


def test_load_frame_image_refusals_name_the_frame():
    with pytest.raises(InputValueError, match=r"^f1: image must be \[3 \| 4, H, W\], got \[2, 2, 4\]$"):
        load_frame_image(Frame("f1", _cam(4, 2), torch.zeros(2, 2, 4)), torch.zeros(3))
    with pytest.raises(FileFormatError, match="^f2: image is 5x2, its camera is 4x2$"):
        load_frame_image(Frame("f2", _cam(4, 2), torch.zeros(3, 2, 5)), torch.zeros(3))
    with pytest.raises(InputValueError, match=r"image must be a floating \[C, H, W\] tensor, got torch.uint8"):
        undistort(torch.zeros(3, 2, 4, dtype=torch.uint8), _cam(4, 2), (0.0, 0, 0, 0))
    with pytest.raises(InputValueError, match="^image is 5x2, its camera is 4x2$"):
        undistort(torch.zeros(3, 2, 5), _cam(4, 2), (0.0, 0, 0, 0))


@pytest.mark.parametrize("d, words", [
    ((0.1, 0.0, 0.0), "4 or 5 finite values"), ((0.1,) * 6, "4 or 5 finite values"),
    ((float("nan"), 0, 0, 0), "4 or 5 finite values"), (("a", 0, 0, 0), "distortion must be (k1, k2, p1, p2[, k3])"),
    (None, "distortion must be (k1, k2, p1, p2[, k3]), got None"),
])
def test_distortion_coefficients_refused(d, words):
    with pytest.raises(InputValueError) as e:
        distort_normalized(torch.zeros(1, 2), d)
    assert words in str(e.value)


def test_distortion_each_coefficient_by_hand():
    x, y = 0.3, -0.2
    r2 = x * x + y * y
    xy = torch.tensor([[x, y]], dtype=torch.float64)
    for d, (wx, wy) in [
        ((0.1, 0, 0, 0), (x * (1 + 0.1 * r2), y * (1 + 0.1 * r2))),
        ((0, 0.1, 0, 0), (x * (1 + 0.1 * r2 ** 2), y * (1 + 0.1 * r2 ** 2))),
        ((0, 0, 0, 0, 0.1), (x * (1 + 0.1 * r2 ** 3), y * (1 + 0.1 * r2 ** 3))),
        ((0, 0, 0.1, 0), (x + 2 * 0.1 * x * y, y + 0.1 * (r2 + 2 * y * y))),
        ((0, 0, 0, 0.1), (x + 0.1 * (r2 + 2 * x * x), y + 2 * 0.1 * x * y)),
    ]:
        got = distort_normalized(xy, d)[0].tolist()
        assert got == pytest.approx([wx, wy], abs=1e-15), d


def test_read_image_modes_from_pillow_files(tmp_path):
    from PIL import Image

    g16 = np.array([[0, 65535, 1000]], dtype=np.uint16)
    Image.fromarray(g16).save(tmp_path / "g16.png")
    img = read_image(tmp_path / "g16.png")
    assert img.shape == (3, 1, 3) and img.dtype == torch.float32
    np.testing.assert_allclose(img.numpy(), np.repeat((g16 / 65535.0)[None], 3, 0), rtol=1e-6)
    rgba = np.array([[[255, 0, 0, 128], [0, 51, 0, 255]]], dtype=np.uint8)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    np.testing.assert_allclose(read_image(tmp_path / "a.png").numpy(), rgba.transpose(2, 0, 1) / 255.0, rtol=1e-6)
    Image.fromarray(np.array([[10, 200]], np.uint8), "L").save(tmp_path / "l.png")
    assert read_image(tmp_path / "l.png")[:, 0, 1].tolist() == pytest.approx([200 / 255] * 3)
    pal = Image.new("P", (2, 1))
    pal.putpalette([255, 0, 0, 0, 0, 255] + [0] * 762)
    pal.putpixel((1, 0), 1)
    pal.info["transparency"] = 0
    pal.save(tmp_path / "p.png", transparency=0)
    p = read_image(tmp_path / "p.png")
    assert p.shape[0] == 4 and p[3].tolist() == [[0.0, 1.0]] and p[:3, 0, 1].tolist() == [0.0, 0.0, 1.0]
    assert image_size(tmp_path / "a.png") == (2, 1)
    (tmp_path / "bad.png").write_bytes(b"not an image")
    with pytest.raises(FileFormatError, match=r"bad.png: cannot decode the image \("):
        read_image(tmp_path / "bad.png")
    with pytest.raises(FileFormatError, match=r"bad.png: cannot read the image header \("):
        image_size(tmp_path / "bad.png")
    for fn in (read_image, image_size):
        with pytest.raises(FileFormatError, match="gone.png: image file not found"):
            fn(tmp_path / "gone.png")


pycolmap = pytest.importorskip("pycolmap")


cv2 = pytest.importorskip("cv2")


W, H = 40, 30


#: one camera of every supported model: (model, params) at W x H
MODELS = {
    1: ("SIMPLE_PINHOLE", [42.0, 20.3, 14.6]),
    2: ("PINHOLE", [41.0, 43.5, 19.2, 15.7]),
    3: ("SIMPLE_RADIAL", [40.0, 20.5, 15.2, -0.12]),
    4: ("RADIAL", [44.0, 19.6, 14.9, 0.08, -0.03]),
    5: ("OPENCV", [45.0, 43.0, 20.7, 15.4, -0.15, 0.04, 0.003, -0.002]),
}


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return pycolmap.Rotation3d(q / np.linalg.norm(q)).matrix()


def _reconstruction(n_images: int = 10, models: dict | None = None, seed: int = 0, size: tuple[int, int] = (W, H)):
    """A pycolmap reconstruction: cameras of ``models``, images named out of order with random poses
    (cameras looking at the origin from ~4 units), some with 2D points, and 3D points with tracks."""
    rng = np.random.default_rng(seed)
    models = MODELS if models is None else models
    rec = pycolmap.Reconstruction()
    for cid, (model, params) in models.items():
        cam = pycolmap.Camera.create_from_model_name(cid, model, 1.0, *size)
        cam.params = params
        rec.add_camera_with_trivial_rig(cam)
    cam_ids = list(models)
    for i in range(n_images):
        image_id = 100 + i
        r = _rotation(rng)
        t = np.array([0.0, 0.0, 4.0]) + rng.normal(scale=0.2, size=3)
        kps = rng.uniform(0, min(size), size=(25 if i % 2 else 0, 2))  # images without 2D points too
        img = pycolmap.Image(name=f"img_{(7 * i) % n_images:03d}.png", keypoints=kps,
                             camera_id=cam_ids[i % len(cam_ids)], image_id=image_id)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(r), t))
    for j in range(25):
        track = pycolmap.Track()
        for i in range(1, n_images, 2):
            if (i + j) % 3 == 0:
                track.add_element(100 + i, j)
        rec.add_point3D(rng.normal(scale=0.5, size=3), track)
    return rec


def _write_scene(root: Path, rec, *, text: bool = False, sparse: str = "sparse/0",
                 folders: dict[str, tuple[int, int]] | None = None) -> Path:
    """Write ``rec`` under ``root/sparse`` and a PNG per image in each folder (name -> size)."""
    d = root / sparse
    d.mkdir(parents=True, exist_ok=True)
    (rec.write_text if text else rec.write_binary)(str(d))
    rng = np.random.default_rng(1)
    for folder, (w, h) in (folders or {"images": (W, H)}).items():
        (root / folder).mkdir(exist_ok=True)
        for im in rec.images.values():
            Image.fromarray(rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)).save(root / folder / im.name)
    return root


def _cv_k(k: torch.Tensor) -> np.ndarray:
    """Our intrinsics (pixel centres at i + 0.5) as OpenCV's (centres at i)."""
    k = k.double().numpy().copy()
    k[0, 2] -= 0.5
    k[1, 2] -= 0.5
    return k


def _smooth_image(h: int, w: int) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    return torch.stack([0.5 + 0.4 * torch.sin(xx / 5.0 + yy / 7.0), 0.5 + 0.4 * torch.cos(yy / 4.0),
                        (xx + yy) / (w + h)]).float()


@pytest.mark.parametrize("dist", [(-0.15, 0.04, 0.003, -0.002, 0.0), (0.1, -0.05, -0.004, 0.002, 0.01)])
def test_undistort_matches_opencv(dist):
    from controlgs_adapter.state import Camera

    h, w = 48, 64
    k = torch.tensor([[60.0, 0, 33.1], [0, 58.0, 23.7], [0, 0, 1]])
    cam = Camera(torch.eye(4), k, w, h)
    img = _smooth_image(h, w)
    ours = undistort(img, cam, dist).numpy().transpose(1, 2, 0)
    k_cv = _cv_k(k)
    mx, my = cv2.initUndistortRectifyMap(k_cv, np.array(dist), None, k_cv, (w, h), cv2.CV_32FC1)
    ref = cv2.remap(img.numpy().transpose(1, 2, 0), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    inside = (mx > 1) & (mx < w - 2) & (my > 1) & (my < h - 2)  # away from the border
    assert inside.mean() > 0.8
    # float maps: OpenCV samples exactly (a half-pixel convention error would be ~1e-2 here)
    assert np.abs(ours - ref)[inside].max() < 1e-5
    assert np.abs(ours - img.numpy().transpose(1, 2, 0))[inside].max() > 0.05  # it did move pixels
    # cv2.undistort quantises its maps to 1/32 px: a gradient-bounded tolerance
    undist = cv2.undistort(img.numpy().transpose(1, 2, 0), k_cv, np.array(dist), newCameraMatrix=k_cv)
    assert np.abs(ours - undist)[inside].max() < 5e-3


def test_views_load_undistorted_images(tmp_path):
    rec = _reconstruction(n_images=5)
    scene = read_colmap(_write_scene(tmp_path, rec), holdout=0)
    views = scene.views("train")
    for i, f in enumerate(views.frames):
        raw = read_image(f.source)
        if f.distortion is None:
            assert torch.equal(views.image(i), raw)
        else:
            assert torch.allclose(views.image(i), undistort(raw, f.camera, f.distortion))
            k_cv = _cv_k(f.camera.intrinsics)
            mx, my = cv2.initUndistortRectifyMap(k_cv, np.array(f.distortion), None, k_cv, (W, H), cv2.CV_32FC1)
            ref = cv2.remap(raw.numpy().transpose(1, 2, 0), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            inside = (mx > 1) & (mx < W - 2) & (my > 1) & (my < H - 2)
            assert inside.mean() > 0.6  # a 40 x 30 image: most of it
            assert np.abs(views.image(i).numpy().transpose(1, 2, 0) - ref)[inside].max() < 1e-4


def test_undistort_points_inverts_the_model():
    k = torch.tensor([[500.0, 0, 320.5], [0, 510.0, 240.2], [0, 0, 1]], dtype=torch.float64)
    dist = (-0.28, 0.09, 0.001, -0.0015, -0.01)
    uv = torch.rand(200, 2, dtype=torch.float64) * torch.tensor([640.0, 480.0])
    xy = torch.stack([(uv[:, 0] - k[0, 2]) / k[0, 0], (uv[:, 1] - k[1, 2]) / k[1, 1]], -1)
    d = distort_normalized(xy, dist)
    uv_d = torch.stack([d[:, 0] * k[0, 0] + k[0, 2], d[:, 1] * k[1, 1] + k[1, 2]], -1)
    assert torch.allclose(undistort_points(uv_d, k, dist), uv, atol=1e-6)
    with pytest.raises(InputValueError, match="distortion"):
        undistort_points(uv_d, k, (0.1, 0.2))


# --------------------------------------------------------------------------- undistort_points
_K = torch.tensor([[300.0, 0, 160], [0, 280.0, 120], [0, 0, 1]], dtype=torch.float64)


_DIST = (-0.21, 0.05, 0.003, -0.002, 0.04)  # k3 != 0


def _newton_reference(uv: torch.Tensor, dist, steps: int) -> torch.Tensor:
    """Newton's method on distort_normalized(xy) = target with the Jacobian from autograd (float64)."""
    fx, fy, cx, cy = _K[0, 0], _K[1, 1], _K[0, 2], _K[1, 2]
    out = []
    for row in uv.double():
        target = torch.stack([(row[0] - cx) / fx, (row[1] - cy) / fy])
        xy = target.clone()
        for _ in range(steps):
            jac = torch.autograd.functional.jacobian(lambda v: distort_normalized(v, dist), xy)
            xy = xy - torch.linalg.solve(jac, distort_normalized(xy, dist) - target)
        out.append(torch.stack([fx * xy[0] + cx, fy * xy[1] + cy]))
    return torch.stack(out)


@pytest.mark.parametrize("steps", [1, 2])
def test_undistort_points_newton_steps_use_the_exact_jacobian(steps):
    uv = torch.tensor([[5.0, 7.0], [310.0, 20.0], [160.0, 230.0], [40.0, 200.0], [290.0, 215.0]], dtype=torch.float64)
    got = undistort_points(uv, _K, _DIST, iterations=steps)
    want = _newton_reference(uv, _DIST, steps)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-9)
    assert not torch.allclose(got, uv, atol=1e-3)  # the steps moved the points


def test_undistort_points_with_k3_inverts_opencv_projection():
    cv2 = pytest.importorskip("cv2")
    # ground truth: undistorted pixels -> OpenCV projectPoints with distortion -> undistort_points back
    truth = torch.tensor([[10.0, 15.0], [300.0, 25.0], [150.0, 110.0], [30.0, 225.0], [305.0, 230.0]], dtype=torch.float64)
    fx, fy, cx, cy = 300.0, 280.0, 160.0, 120.0
    obj = np.stack([(truth[:, 0].numpy() - cx) / fx, (truth[:, 1].numpy() - cy) / fy, np.ones(5)], axis=1)
    distorted, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), _K.numpy(), np.array(_DIST))
    uv = torch.from_numpy(distorted.reshape(-1, 2))
    torch.testing.assert_close(undistort_points(uv, _K, _DIST), truth, rtol=0, atol=1e-7)
    # and against OpenCV's own inverse (its iterative solver, many iterations)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    cv_back = cv2.undistortPoints(distorted, _K.numpy(), np.array(_DIST), R=None, P=_K.numpy(), criteria=crit).reshape(-1, 2)
    np.testing.assert_allclose(undistort_points(uv, _K, _DIST).numpy(), cv_back, atol=1e-5)
    assert undistort_points(uv.float(), _K, _DIST).dtype == torch.float32


def test_undistort_points_default_20_iterations_converge():
    k = torch.tensor([[300.0, 0, 160], [0, 280.0, 120], [0, 0, 1]], dtype=torch.float64)
    dist = (-0.3, 0.1, 0.002, -0.001, 0.02)
    uv = torch.tensor([[5.0, 7.0], [310.0, 230.0]], dtype=torch.float64)
    default = undistort_points(uv, k, dist)
    assert torch.equal(default, undistort_points(uv, k, dist, iterations=20))
    assert not torch.allclose(default, undistort_points(uv, k, dist, iterations=1), atol=1e-6)
    # converged: distorting the result gives back the input
    xy = torch.stack([(default[:, 0] - 160) / 300, (default[:, 1] - 120) / 280], dim=-1)
    d = distort_normalized(xy, dist)
    torch.testing.assert_close(torch.stack([300 * d[:, 0] + 160, 280 * d[:, 1] + 120], dim=-1), uv, rtol=0, atol=1e-9)


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


def re_escape(s: str) -> str:
    import re

    return re.escape(s)


def test_undistort_points_refuses_a_bad_shape():
    k = torch.tensor([[10.0, 0, 4], [0, 10.0, 3], [0, 0, 1]])
    for uv in (torch.zeros(3, 3), torch.zeros(2)):
        with pytest.raises(InputValueError, match=rf"uv must be \[N, 2\], got {re_escape(str(list(uv.shape)))}"):
            undistort_points(uv, k, (0.1, 0.0, 0.0, 0.0))
    # the identity without distortion
    uv = torch.tensor([[1.0, 2.0], [7.5, 0.5]])
    assert torch.allclose(undistort_points(uv, k, (0.0, 0.0, 0.0, 0.0)), uv)
