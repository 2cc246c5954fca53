"""Tests of ``controlgs_adapter.datasets.images``: decoding image files, the frame image checks, and the OpenCV
radial-tangential distortion (worked out per coefficient, against OpenCV, and its Newton inverse ``undistort_points``)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from helpers.colmap_models import H, W, needs_cv2, needs_pycolmap, opencv_k, reconstruction, write_reconstruction
from helpers.dataset_views import pinhole
from PIL import Image

from controlgs_adapter.datasets import read_colmap, undistort_points
from controlgs_adapter.datasets.base import Frame
from controlgs_adapter.datasets.images import distort_normalized, image_size, load_frame_image, read_image, undistort
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera

#: intrinsics of a 320 x 240 camera and distortion with k3 != 0
_K = torch.tensor([[300.0, 0, 160], [0, 280.0, 120], [0, 0, 1]], dtype=torch.float64)
_DIST = (-0.21, 0.05, 0.003, -0.002, 0.04)


def _smooth_image(h: int, w: int) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    return torch.stack([0.5 + 0.4 * torch.sin(xx / 5.0 + yy / 7.0), 0.5 + 0.4 * torch.cos(yy / 4.0),
                        (xx + yy) / (w + h)]).float()


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


# ----------------------------------------------------------------------------- image files and frames

def test_read_image_modes_from_pillow_files(tmp_path):
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


def test_load_frame_image_refusals_name_the_frame():
    with pytest.raises(InputValueError, match=r"^f1: image must be \[3 \| 4, H, W\], got \[2, 2, 4\]$"):
        load_frame_image(Frame("f1", pinhole(4, 2, 10.0, 12.0), torch.zeros(2, 2, 4)), torch.zeros(3))
    with pytest.raises(FileFormatError, match="^f2: image is 5x2, its camera is 4x2$"):
        load_frame_image(Frame("f2", pinhole(4, 2, 10.0, 12.0), torch.zeros(3, 2, 5)), torch.zeros(3))
    with pytest.raises(InputValueError, match=r"image must be a floating \[C, H, W\] tensor, got torch.uint8"):
        undistort(torch.zeros(3, 2, 4, dtype=torch.uint8), pinhole(4, 2, 10.0, 12.0), (0.0, 0, 0, 0))
    with pytest.raises(InputValueError, match="^image is 5x2, its camera is 4x2$"):
        undistort(torch.zeros(3, 2, 5), pinhole(4, 2, 10.0, 12.0), (0.0, 0, 0, 0))


# ----------------------------------------------------------------------------- distortion

def test_distortion_of_each_coefficient():
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


@pytest.mark.parametrize("d", [(0.1, 0.0, 0.0), (0.1,) * 6, (float("nan"), 0, 0, 0), ("a", 0, 0, 0), None])
def test_distortion_coefficients_refused_naming_the_value(d):
    with pytest.raises(InputValueError, match=r"distortion.*got " + re.escape(repr(d))):
        distort_normalized(torch.zeros(1, 2), d)


@needs_cv2
@pytest.mark.parametrize("dist", [(-0.15, 0.04, 0.003, -0.002, 0.0), (0.1, -0.05, -0.004, 0.002, 0.01)])
def test_undistort_matches_opencv(dist):
    import cv2

    h, w = 48, 64
    k = torch.tensor([[60.0, 0, 33.1], [0, 58.0, 23.7], [0, 0, 1]])
    cam = Camera(torch.eye(4), k, w, h)
    img = _smooth_image(h, w)
    ours = undistort(img, cam, dist).numpy().transpose(1, 2, 0)
    k_cv = opencv_k(k)
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


@needs_pycolmap
@needs_cv2
def test_views_load_undistorted_images(tmp_path):
    import cv2

    rec = reconstruction(n_images=5)
    scene = read_colmap(write_reconstruction(tmp_path, rec), holdout=0)
    views = scene.views("train")
    for i, f in enumerate(views.frames):
        raw = read_image(f.source)
        if f.distortion is None:
            assert torch.equal(views.image(i), raw)
        else:
            assert torch.allclose(views.image(i), undistort(raw, f.camera, f.distortion))
            k_cv = opencv_k(f.camera.intrinsics)
            mx, my = cv2.initUndistortRectifyMap(k_cv, np.array(f.distortion), None, k_cv, (W, H), cv2.CV_32FC1)
            ref = cv2.remap(raw.numpy().transpose(1, 2, 0), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            inside = (mx > 1) & (mx < W - 2) & (my > 1) & (my < H - 2)
            assert inside.mean() > 0.6  # a 40 x 30 image: most of it
            assert np.abs(views.image(i).numpy().transpose(1, 2, 0) - ref)[inside].max() < 1e-4


# ----------------------------------------------------------------------------- undistort_points

def test_undistort_points_inverts_the_distortion():
    """Distorting the result gives back the input (k3 included); 20 iterations by default, where one is not
    enough; Newton's method converges quadratically: 4 iterations land on the pinhole position to float64
    precision (a wrong Jacobian term converges only linearly, ~1e-5 px off). Without distortion: the identity."""
    k = torch.tensor([[500.0, 0, 320.5], [0, 510.0, 240.2], [0, 0, 1]], dtype=torch.float64)
    dist = (-0.28, 0.09, 0.001, -0.0015, -0.01)
    uv = torch.rand(200, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * torch.tensor([640.0, 480.0])
    xy = torch.stack([(uv[:, 0] - k[0, 2]) / k[0, 0], (uv[:, 1] - k[1, 2]) / k[1, 1]], -1)
    d = distort_normalized(xy, dist)
    uv_d = torch.stack([d[:, 0] * k[0, 0] + k[0, 2], d[:, 1] * k[1, 1] + k[1, 2]], -1)
    assert torch.allclose(undistort_points(uv_d, k, dist), uv, atol=1e-6)
    assert torch.equal(undistort_points(uv_d, k, dist), undistort_points(uv_d, k, dist, iterations=20))
    assert not torch.allclose(undistort_points(uv_d, k, dist), undistort_points(uv_d, k, dist, iterations=1), atol=1e-6)
    # the forward model in numpy from the module docstring's formula, on a grid of normalised points
    k1, k2, p1, p2, k3 = d5 = (-0.2, 0.05, 0.02, -0.015, 0.01)
    g = np.linspace(-0.6, 0.6, 7)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    fx, fy, cx, cy = 100.0, 90.0, 40.5, 30.25
    k = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    distorted = torch.from_numpy(np.stack([fx * xd + cx, fy * yd + cy], axis=-1))
    got = undistort_points(distorted, k, d5, iterations=4).numpy()
    assert np.abs(got - np.stack([fx * x + cx, fy * y + cy], axis=-1)).max() < 1e-9
    plain = torch.tensor([[1.0, 2.0], [7.5, 0.5]])
    assert torch.allclose(undistort_points(plain, k.float(), (0.0, 0.0, 0.0, 0.0)), plain)


@pytest.mark.parametrize("steps", [1, 2])
def test_undistort_points_newton_steps_use_the_exact_jacobian(steps):
    uv = torch.tensor([[5.0, 7.0], [310.0, 20.0], [160.0, 230.0], [40.0, 200.0], [290.0, 215.0]], dtype=torch.float64)
    got = undistort_points(uv, _K, _DIST, iterations=steps)
    want = _newton_reference(uv, _DIST, steps)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-9)
    assert not torch.allclose(got, uv, atol=1e-3)  # the steps moved the points


@needs_cv2
def test_undistort_points_with_k3_inverts_opencv_projection():
    import cv2

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


def test_undistort_points_refusals():
    k = torch.tensor([[10.0, 0, 4], [0, 10.0, 3], [0, 0, 1]])
    for uv in (torch.zeros(3, 3), torch.zeros(2)):
        with pytest.raises(InputValueError, match=rf"uv must be \[N, 2\], got {re.escape(str(list(uv.shape)))}"):
            undistort_points(uv, k, (0.1, 0.0, 0.0, 0.0))
    with pytest.raises(InputValueError, match="distortion"):
        undistort_points(torch.zeros(1, 2), k, (0.1, 0.2))
