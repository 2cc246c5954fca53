"""The built-in scene: determinism, exact anti-aliased coverage and texture filtering against an
independent float64 numpy brute force."""

import math

import numpy as np
import pytest
import torch

pytest.importorskip("skimage")

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.scene import (TexturedPlane, load_builtin_scene, look_at, mip_pyramid, render_planes,
                                     TEXTURES, load_texture)

SIZE, DIST, FOV = 16, 5.0, 40.0


def _front_plane(texture: torch.Tensor, u0: float, u1: float, v0: float, v1: float, size: int = SIZE) -> TexturedPlane:
    """A plane at z=0 facing the camera at (0, 0, DIST) whose image covers pixels [u0, u1] x [v0, v1]."""
    c, focal = size / 2.0, size / (2.0 * math.tan(math.radians(FOV) / 2.0))
    x0, x1 = (u0 - c) * DIST / focal, (u1 - c) * DIST / focal
    y0, y1 = -(v0 - c) * DIST / focal, -(v1 - c) * DIST / focal
    center = torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2, 0.0], dtype=torch.float64)
    right = torch.tensor([(x1 - x0) / 2, 0.0, 0.0], dtype=torch.float64)
    down = torch.tensor([0.0, (y1 - y0) / 2, 0.0], dtype=torch.float64)
    return TexturedPlane("p", center, right, down, texture)


def _camera(size: int = SIZE):
    return look_at((0.0, 0.0, DIST), (0.0, 0.0, 0.0), size=size, fov_deg=FOV)


def _box_coverage(lo: float, hi: float, n: int) -> np.ndarray:
    """Exact fraction of each pixel [i, i+1) inside [lo, hi]."""
    i = np.arange(n, dtype=np.float64)
    return np.clip(np.minimum(i + 1, hi) - np.maximum(i, lo), 0.0, 1.0)


def test_scene_is_deterministic_and_split():
    a = load_builtin_scene("ar", 24, views=8, test_every=4, samples=2)
    b = load_builtin_scene("ar", 24, views=8, test_every=4, samples=2)
    assert torch.equal(a.train_images, b.train_images) and torch.equal(a.test_images, b.test_images)
    assert a.train_images.shape == (6, 3, 24, 24) and a.test_images.shape == (2, 3, 24, 24)
    assert float(a.train_images.min()) >= 0.0 and float(a.train_images.max()) <= 1.0
    # the AR variant shows black background, the views differ from each other
    assert float((a.train_images.sum(1) == 0).float().mean()) > 0.1
    assert not torch.equal(a.train_images[0], a.train_images[1])
    xyz, rgb = a.points(0.2)
    assert xyz.shape == rgb.shape and xyz.shape[1] == 3 and xyz.shape[0] > 50


def test_vr_variant_has_no_background():
    s = load_builtin_scene("vr", 16, views=4, test_every=2, samples=1)
    for cam in s.train_cameras + s.test_cameras:
        _, coverage, depth = render_planes(s.planes, cam, samples=1)
        assert float(coverage.min()) == 1.0 and float(depth.min()) > 0.0


@pytest.mark.parametrize("samples", [4, 8])
def test_edge_coverage_matches_area_fraction(samples):
    """A white rectangle on black: each pixel equals the exact area it covers, up to the
    sub-sample quantisation (exact where edges sit on sub-sample boundaries)."""
    white = torch.ones(3, 4, 4, dtype=torch.float64)
    u0, u1, v0, v1 = 3.25, 12.75, 2.5, 9.0  # on quarter-pixel boundaries: exact for n = 4, 8
    img, cov, _ = render_planes([_front_plane(white, u0, u1, v0, v1)], _camera(), samples=samples)
    exact = np.outer(_box_coverage(v0, v1, SIZE), _box_coverage(u0, u1, SIZE))
    np.testing.assert_allclose(cov[0].numpy(), exact, atol=1e-12)
    np.testing.assert_allclose(img.numpy(), np.broadcast_to(exact, (3, SIZE, SIZE)), atol=1e-12)
    # an arbitrary edge position: error bounded by one sub-sample row/column per edge
    u0, u1 = 3.1, 12.93
    _, cov, _ = render_planes([_front_plane(white, u0, u1, v0, v1)], _camera(), samples=samples)
    exact = np.outer(_box_coverage(v0, v1, SIZE), _box_coverage(u0, u1, SIZE))
    assert np.abs(cov[0].numpy() - exact).max() <= 1.0 / samples + 1e-9


def _numpy_bilinear(tex: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Bilinear lookup at continuous texel coordinates (pixel centres at i + 0.5), edges clamped."""
    h, w = tex.shape[1:]
    x, y = np.clip(tx - 0.5, 0, w - 1), np.clip(ty - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    return (tex[:, y0, x0] * (1 - fx) * (1 - fy) + tex[:, y0, x1] * fx * (1 - fy)
            + tex[:, y1, x0] * (1 - fx) * fy + tex[:, y1, x1] * fx * fy)


def test_texture_filtering_matches_box_integral():
    """Pixels of a minified photograph equal the box-filter integral of the bilinear texture
    (independent brute force with 32 x 32 point samples per pixel, float64 numpy)."""
    tex = load_texture("astronaut")[:, ::2, ::2].contiguous()  # 256 x 256, about 25 texels per pixel
    size = 24
    u0, u1, v0, v1 = 7.0, 17.0, 6.0, 16.0
    cam, plane = _camera(size), _front_plane(tex, u0, u1, v0, v1, size)
    n = 32
    offs = (np.arange(n) + 0.5) / n
    us = (np.arange(size)[:, None] + offs).reshape(-1)
    a = (us - u0) / (u1 - u0) * tex.shape[2]  # texel x of every sub-sample column
    b = (us - v0) / (v1 - v0) * tex.shape[1]
    inside_a, inside_b = (a >= 0) & (a <= tex.shape[2]), (b >= 0) & (b <= tex.shape[1])
    ty, tx = np.meshgrid(b, a, indexing="ij")
    vals = _numpy_bilinear(tex.numpy(), tx, ty) * (inside_b[:, None] & inside_a[None, :])
    ref = vals.reshape(3, size, n, size, n).mean(axis=(2, 4))
    errs = {}
    for samples in (1, 4):
        img, _, _ = render_planes([plane], cam, samples=samples)
        errs[samples] = np.abs(img.numpy() - ref)[:, 6:16, 7:17].mean()
    assert errs[4] < 0.015, errs  # measured 0.0098 (n=1: 0.062, n=8: 0.0031)
    assert errs[1] > 3 * errs[4], errs


def test_mip_pyramid_preserves_mean_and_halves():
    tex = torch.rand(3, 37, 20, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    levels = mip_pyramid(tex)
    assert [tuple(l.shape[1:]) for l in levels[:3]] == [(37, 20), (19, 10), (10, 5)]
    assert levels[-1].shape[1:] == (1, 1)
    np.testing.assert_allclose(levels[-1].reshape(3).numpy(), tex.mean(dim=(1, 2)).numpy(), atol=0.02)


def test_textures_have_a_recorded_licence():
    for name, info in TEXTURES.items():
        assert "CC0" in info.licence or "public domain" in info.licence
        t = load_texture(name)
        assert t.shape[0] == 3 and 0.0 <= float(t.min()) and float(t.max()) <= 1.0


def test_bad_arguments_raise_clear_errors():
    with pytest.raises(InputValueError, match="variant"):
        load_builtin_scene("xr", 32)
    with pytest.raises(InputValueError, match="resolution"):
        load_builtin_scene("ar", 8)
    with pytest.raises(InputValueError, match="samples"):
        render_planes([], _camera(), samples=0)


def test_ground_truth_cache_round_trip(tmp_path):
    a = load_builtin_scene("ar", 16, views=4, test_every=2, samples=1, cache=tmp_path)
    files = list(tmp_path.iterdir())
    assert len(files) == 1
    b = load_builtin_scene("ar", 16, views=4, test_every=2, samples=1, cache=tmp_path)
    assert torch.equal(a.train_images, b.train_images) and torch.equal(a.test_images, b.test_images)
    files[0].write_bytes(b"garbage")  # a corrupt cache is rendered again, not trusted
    c = load_builtin_scene("ar", 16, views=4, test_every=2, samples=1, cache=tmp_path)
    assert torch.equal(a.train_images, c.train_images)
