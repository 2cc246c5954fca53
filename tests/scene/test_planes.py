"""Tests of ``controlgs_adapter.scene.planes``: textured planes (construction, trilinear mip-mapped sampling,
tiling), the plane renderer (coverage, nearest plane, depth, background, texture filtering, mip level) and
the point grid sampled from a plane."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.scene import TexturedPlane, load_texture, look_at, render_planes
from controlgs_adapter.scene.planes import plane_points
from controlgs_adapter.state import Camera

pytest.importorskip("skimage")  # the built-in textures

F64 = torch.float64
SIZE, DIST, FOV = 16, 5.0, 40.0


def _t(*v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


def _camera_at(distance: float = DIST, size: int = SIZE, fov_deg: float = FOV) -> Camera:
    """A square camera on +z at ``distance`` looking at the origin."""
    return look_at((0.0, 0.0, distance), (0.0, 0.0, 0.0), size=size, fov_deg=fov_deg)


def _pinhole(width: int, height: int, f: float, t: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Camera:
    """Float64 camera looking down +z (OpenCV axes) with world-to-camera translation ``t``, principal point at the
    image centre."""
    w2c = torch.eye(4, dtype=F64)
    w2c[:3, 3] = _t(*t)
    k = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=F64)
    return Camera(w2c, k, width, height)


def _front_plane(texture: torch.Tensor, u0: float, u1: float, v0: float, v1: float, size: int = SIZE) -> TexturedPlane:
    """A plane at z=0 facing the camera at (0, 0, DIST) whose image covers pixels [u0, u1] x [v0, v1]."""
    c, focal = size / 2.0, size / (2.0 * math.tan(math.radians(FOV) / 2.0))
    x0, x1 = (u0 - c) * DIST / focal, (u1 - c) * DIST / focal
    y0, y1 = -(v0 - c) * DIST / focal, -(v1 - c) * DIST / focal
    return TexturedPlane("p", _t((x0 + x1) / 2, (y0 + y1) / 2, 0.0), _t((x1 - x0) / 2, 0.0, 0.0), _t(0.0, (y1 - y0) / 2, 0.0),
                         texture)


def _plane_over_pixels(cam: Camera, z: float, cols: tuple[int, int], rows: tuple[int, int]) -> TexturedPlane:
    """A fronto-parallel plane at depth ``z`` whose image is exactly pixel columns ``[c0, c1)`` and
    rows ``[r0, r1)`` (edges on pixel boundaries: u = fx x / z + cx, v = fy y / z + cy)."""
    k = cam.intrinsics
    x0, x1 = ((c - float(k[0, 2])) * z / float(k[0, 0]) for c in cols)
    y0, y1 = ((r - float(k[1, 2])) * z / float(k[1, 1]) for r in rows)
    center = torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2, z], dtype=F64)
    right = torch.tensor([(x1 - x0) / 2, 0.0, 0.0], dtype=F64)
    down = torch.tensor([0.0, (y1 - y0) / 2, 0.0], dtype=F64)
    return TexturedPlane("p", center, right, down, torch.full((3, 4, 4), 0.5, dtype=F64))


def _flat(color, center, half_w, half_h, w_tex=2):
    """A plane of constant ``color`` centred at ``center``, facing +z, half sizes ``half_w x half_h``."""
    tex = torch.tensor(color, dtype=F64)[:, None, None].expand(3, 2, w_tex).clone()
    return TexturedPlane("p", _t(*center), _t(half_w, 0, 0), _t(0, -half_h, 0), tex)


def _box_coverage(lo: float, hi: float, n: int) -> np.ndarray:
    """Exact fraction of each pixel [i, i+1) inside [lo, hi]."""
    i = np.arange(n, dtype=np.float64)
    return np.clip(np.minimum(i + 1, hi) - np.maximum(i, lo), 0.0, 1.0)


def _numpy_bilinear(tex: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Bilinear lookup at continuous texel coordinates (pixel centres at i + 0.5), edges clamped."""
    h, w = tex.shape[1:]
    x, y = np.clip(tx - 0.5, 0, w - 1), np.clip(ty - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    return (tex[:, y0, x0] * (1 - fx) * (1 - fy) + tex[:, y0, x1] * fx * (1 - fy)
            + tex[:, y1, x0] * (1 - fx) * fy + tex[:, y1, x1] * fx * fy)


def _bilinear(tex: np.ndarray, a: float, b: float) -> np.ndarray:
    """Bilinear texel lookup at plane coordinates a, b in [-1, 1]."""
    h, w = tex.shape[1:]
    return _numpy_bilinear(tex, np.asarray((a + 1) / 2 * w), np.asarray((b + 1) / 2 * h))


def _level_coded(plane: TexturedPlane, n_levels: int = 8) -> TexturedPlane:
    """``plane`` with mip level l replaced by the constant l / 10: a rendered colour reads back the lod."""
    plane.levels = [torch.full((3, 1, 1), lvl / 10.0, dtype=F64) for lvl in range(n_levels)]
    return plane


def _texel(plane: TexturedPlane, cam, u: float, v: float) -> np.ndarray:
    """Texel coordinates (x, y) where the ray through pixel position (u, v) meets ``plane`` (float64 brute force)."""
    k, w2c = cam.intrinsics.double().numpy(), cam.world_to_camera.double().numpy()
    d = w2c[:3, :3].T @ np.array([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], 1.0])
    o = cam.center.double().numpy()
    c, r, dn = plane.center.numpy(), plane.right.numpy(), plane.down.numpy()
    nrm = np.cross(r, dn)
    p = o + d * ((c - o) @ nrm) / (d @ nrm)
    h, w = plane.texture.shape[-2:]
    return np.array([(p - c) @ r / (r @ r) * w * plane.repeat[0] / 2, (p - c) @ dn / (dn @ dn) * h * plane.repeat[1] / 2])


# ----------------------------------------------------------------------------- TexturedPlane

def test_make_defaults_face_plus_z_untiled():
    p = TexturedPlane.make("p", "brick", (1.0, 2.0, 3.0), 2.0, 4.0)
    torch.testing.assert_close(p.right, _t(1.0, 0.0, 0.0), atol=1e-15, rtol=0)
    torch.testing.assert_close(p.down, _t(0.0, -2.0, 0.0), atol=1e-15, rtol=0)
    torch.testing.assert_close(p.normal, _t(0.0, 0.0, -1.0), atol=1e-15, rtol=0)
    assert p.repeat == (1, 1)
    q = TexturedPlane.make("q", "brick", (0.0, 0.0, 0.0), 2.0, 1.0)  # yaw 0, pitch 0: right (w/2, 0, 0), down (0, -h/2, 0)
    assert q.right.tolist() == [1.0, 0.0, 0.0] and q.down.tolist() == [0.0, -0.5, 0.0]


def test_plane_refusals_name_the_plane():
    tex = torch.rand(3, 4, 4, dtype=F64)
    # orthogonality is relative: |r.d| <= 1e-9 |r| |d| (here |r| |d| = 1e6, bound 1e-3)
    TexturedPlane("ok", _t(0, 0, 0), _t(1e3, 0, 0), _t(1e-7, 1e3, 0), tex)  # r.d = 1e-4: accepted
    with pytest.raises(InputValueError, match="plane 'skew': right and down must be orthogonal"):
        TexturedPlane("skew", _t(0, 0, 0), _t(1e3, 0, 0), _t(2e-6, 1e3, 0), tex)  # r.d = 2e-3
    with pytest.raises(InputValueError, match="plane 'skew2': right and down must be orthogonal"):
        TexturedPlane("skew2", _t(0, 0, 0), _t(1, 0, 0), _t(0.1, 1, 0), tex)
    for rep in ((0, 1), (1, 0), (1, 1, 1), (2,)):
        with pytest.raises(InputValueError, match=r"plane 'r': repeat must be two integers >= 1"):
            TexturedPlane("r", _t(0, 0, 0), _t(1, 0, 0), _t(0, 1, 0), tex, rep)
    p = TexturedPlane("f", _t(0, 0, 0), _t(1, 0, 0), _t(0, 1, 0), tex.float(), (2.0, 3.0))  # type: ignore[arg-type]
    assert p.repeat == (2, 3) and type(p.repeat[0]) is int and p.texture.dtype == F64 and p.center.dtype == F64
    with pytest.raises(InputValueError, match="center"):
        TexturedPlane("n", _t(0, math.nan, 0), _t(1, 0, 0), _t(0, 1, 0), tex)
    with pytest.raises(ShapeError, match="texture must have shape"):
        TexturedPlane("n", _t(0, 0, 0), _t(1, 0, 0), _t(0, 1, 0), torch.rand(4, 4, dtype=F64))
    # a NaN or Inf texel would spread through every mip level above it and blank the plane's renders
    for bad in (float("nan"), float("inf")):
        tex = torch.full((3, 4, 4), 0.5, dtype=F64)
        tex[1, 2, 3] = bad
        with pytest.raises(InputValueError, match=r"texture contains 1 non-finite value"):
            TexturedPlane("p", _t(0, 0, 4), _t(0.5, 0, 0), _t(0, 0.5, 0), tex)


def test_sample_blends_bilinear_lookups_of_two_mip_levels():
    g = torch.Generator().manual_seed(3)
    tex = torch.rand(3, 6, 10, dtype=F64, generator=g)
    p = TexturedPlane("p", _t(0, 0, 0), _t(1, 0, 0), _t(0, 1, 0), tex)
    lv = [lvl.numpy() for lvl in p.levels]
    assert [lvl.shape[1:] for lvl in lv] == [(6, 10), (3, 5), (2, 3), (1, 2), (1, 1)]
    a = _t(-0.93, -0.3, 0.0, 0.41, 0.77, 0.99)
    b = _t(0.8, -0.61, 0.05, -0.99, 0.33, 0.0)
    ref0 = np.stack([_bilinear(lv[0], float(x), float(y)) for x, y in zip(a, b)])
    ref1 = np.stack([_bilinear(lv[1], float(x), float(y)) for x, y in zip(a, b)])
    ref2 = np.stack([_bilinear(lv[2], float(x), float(y)) for x, y in zip(a, b)])
    z = torch.zeros(6, dtype=F64)
    np.testing.assert_allclose(p.sample(a, b, z).numpy(), ref0, atol=1e-12)
    np.testing.assert_allclose(p.sample(a, b, z - 3.0).numpy(), ref0, atol=1e-12)  # below 0: level 0
    np.testing.assert_allclose(p.sample(a, b, z + 0.25).numpy(), 0.75 * ref0 + 0.25 * ref1, atol=1e-12)
    np.testing.assert_allclose(p.sample(a, b, z + 1.5).numpy(), 0.5 * ref1 + 0.5 * ref2, atol=1e-12)
    top = np.broadcast_to(lv[-1][:, 0, 0], (6, 3))
    np.testing.assert_allclose(p.sample(a, b, z + 4.0).numpy(), top, atol=1e-12)  # the top level: 1 x 1
    np.testing.assert_allclose(p.sample(a, b, z + 50.0).numpy(), top, atol=1e-12)  # above: clamped to it
    # mixed levels in one call: each row on its own level
    lod = _t(0.0, 1.5, 4.0, 0.25, -1.0, 9.0)
    want = np.stack([ref0[0], 0.5 * ref1[1] + 0.5 * ref2[1], top[2], 0.75 * ref0[3] + 0.25 * ref1[3], ref0[4], top[5]])
    np.testing.assert_allclose(p.sample(a, b, lod).numpy(), want, atol=1e-12)
    # lod 0.7 is 0.3 level 0 + 0.7 level 1: at (-0.5, -0.5) of a 4 x 4 texture, level 0 (bilinear) is the mean of
    # texels [0:2, 0:2] and level 1 (2 x 2) is its texel (0, 0)
    tex4 = torch.rand(3, 4, 4, generator=torch.Generator().manual_seed(1), dtype=F64)
    p4 = TexturedPlane("p", _t(0, 0, 0), _t(1, 0, 0), _t(0, 1, 0), tex4)
    a4, b4 = _t(-0.5, 0.5), _t(-0.5, -0.5)
    lvl1 = p4.levels[1]
    assert lvl1.shape == (3, 2, 2)
    want0 = torch.stack([tex4[:, 0:2, 0:2].mean(dim=(1, 2)), tex4[:, 0:2, 2:4].mean(dim=(1, 2))])
    want1 = torch.stack([lvl1[:, 0, 0], lvl1[:, 0, 1]])
    for lod in (0.0, 0.3, 0.7, 1.0):
        torch.testing.assert_close(p4.sample(a4, b4, torch.full((2,), lod, dtype=F64)), (1 - lod) * want0 + lod * want1,
                                   rtol=1e-12, atol=1e-12)


def test_sample_tiles_by_repeat_in_each_axis():
    tex = torch.rand(3, 8, 12, dtype=F64, generator=torch.Generator().manual_seed(5))
    p1 = TexturedPlane("p", _t(0, 0, 0), _t(1, 0, 0), _t(0, 1, 0), tex)
    p23 = TexturedPlane("q", _t(0, 0, 0), _t(1, 0, 0), _t(0, 1, 0), tex, (2, 3))
    # repeat 2 in a: a' = ((a + 1) mod 1) * 2 - 1, so a = -0.5 -> 0, a = 0.3 -> -0.4
    # repeat 3 in b: b' = ((b + 1) * 1.5 mod 1) * 2 - 1, so b = -0.5 -> 0.5, b = 0.2 -> 0.6
    a, b = _t(-0.5, 0.3, -0.5), _t(-0.5, 0.2, 0.2)
    z = torch.zeros(3, dtype=F64)
    want = p1.sample(_t(0.0, -0.4, 0.0), _t(0.5, 0.6, 0.6), z)
    torch.testing.assert_close(p23.sample(a, b, z), want, atol=1e-12, rtol=0)
    ref = np.stack([_bilinear(tex.numpy(), x, y) for x, y in ((0.0, 0.5), (-0.4, 0.6), (0.0, 0.6))])
    np.testing.assert_allclose(p23.sample(a, b, z).numpy(), ref, atol=1e-12)


# ----------------------------------------------------------------------------- plane_points

def test_plane_points_grid_and_colour():
    tex = torch.rand(3, 4, 8, dtype=F64, generator=torch.Generator().manual_seed(1))
    p = TexturedPlane("p", _t(1.0, 2.0, 3.0), _t(0.5, 0, 0), _t(0, -0.3, 0), tex)
    xyz, rgb = plane_points(p, 0.25)
    # na = ceil(2 * 0.5 / 0.25) = 4, nb = ceil(2 * 0.3 / 0.25) = 3; a = -0.75, -0.25, 0.25, 0.75; b = -2/3, 0, 2/3
    assert xyz.shape == (12, 3) and rgb.shape == (12, 3) and xyz.dtype == F64
    torch.testing.assert_close(xyz[0], _t(1.0 - 0.375, 2.0 + 0.2, 3.0), atol=1e-12, rtol=0)
    torch.testing.assert_close(xyz[1], _t(1.0 - 0.125, 2.0 + 0.2, 3.0), atol=1e-12, rtol=0)  # a runs fastest
    torch.testing.assert_close(xyz[4], _t(1.0 - 0.375, 2.0, 3.0), atol=1e-12, rtol=0)
    torch.testing.assert_close(xyz[11], _t(1.0 + 0.375, 2.0 - 0.2, 3.0), atol=1e-12, rtol=0)
    # one point covers 8 texels / 4 points = 2 texels across: level log2(2) = 1
    aa = _t(-0.75, -0.25, 0.25, 0.75).repeat(3)
    bb = _t(-2 / 3, 0.0, 2 / 3).repeat_interleave(4)
    torch.testing.assert_close(rgb, p.sample(aa, bb, torch.ones(12, dtype=F64)), atol=1e-12, rtol=0)
    # a spacing coarser than the plane: one point at the centre, lod log2(8 / 1) = 3
    xyz, rgb = plane_points(p, 5.0)
    torch.testing.assert_close(xyz, _t(1.0, 2.0, 3.0)[None], atol=1e-12, rtol=0)
    torch.testing.assert_close(rgb, p.sample(_t(0.0), _t(0.0), _t(3.0)), atol=1e-12, rtol=0)
    # finer than a texel: the lod is clamped at level 0 (log2(max(8 / 64, 1)) = 0)
    _, rgb = plane_points(p, 1.0 / 64)
    assert rgb.shape[0] == 64 * 39  # nb = ceil(0.6 * 64) = 39
    # repeat multiplies the texels a point covers: 8 * 2 / 4 = 4 -> level 2
    q = TexturedPlane("q", _t(1.0, 2.0, 3.0), _t(0.5, 0, 0), _t(0, -0.3, 0), tex, (2, 1))
    _, rgb = plane_points(q, 0.25)
    torch.testing.assert_close(rgb, q.sample(aa, bb, torch.full((12,), 2.0, dtype=F64)), atol=1e-12, rtol=0)
    for bad in (0.0, -0.1, math.nan):
        with pytest.raises(InputValueError, match="spacing must be > 0"):
            plane_points(p, bad)


def test_plane_points_and_render_warn_nothing():
    """The built-in scene's plane sampler and renderer run silently: no deprecation or user warning from
    torch (e.g. ``meshgrid`` without ``indexing=``) reaches a user's console. The grid, worked out: a 2 x 1
    plane sampled every 0.5 gives 4 x 2 points at the cell centres, row by row (down) then across (right)."""
    tex = torch.rand(3, 4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    plane = TexturedPlane("p", torch.tensor([0.0, 0.0, 2.0]), torch.tensor([1.0, 0.0, 0.0]),
                          torch.tensor([0.0, 0.5, 0.0]), tex)
    cam = Camera(torch.eye(4, dtype=torch.float64),
                 torch.tensor([[6.0, 0.0, 3.0], [0.0, 6.0, 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64), 6, 4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        xyz, rgb = plane_points(plane, 0.5)
        image, coverage, _ = render_planes([plane], cam, samples=2)
    a = torch.tensor([-0.75, -0.25, 0.25, 0.75], dtype=torch.float64)
    b = torch.tensor([-0.5, 0.5], dtype=torch.float64)
    want = torch.stack([torch.stack([x, 0.5 * y, torch.tensor(2.0, dtype=torch.float64)]) for y in b for x in a])
    torch.testing.assert_close(xyz, want, rtol=0, atol=1e-15)
    assert rgb.shape == (8, 3)
    # the plane spans x in [-1, 1], y in [-0.5, 0.5] at z = 2: u = 6 x / 2 + 3 in [0, 6], v = 6 y / 2 + 2 in [0.5, 3.5]
    assert torch.equal(coverage[0, 1:3], torch.ones(2, 6, dtype=torch.float64))
    assert torch.equal(coverage[0, [0, 3]], torch.full((2, 6), 0.5, dtype=torch.float64))


# ----------------------------------------------------------------------------- render_planes

@pytest.mark.parametrize("samples", [4, 8])
def test_edge_coverage_matches_area_fraction(samples):
    """A white rectangle on black: each pixel equals the exact area it covers, up to the
    sub-sample quantisation (exact where edges sit on sub-sample boundaries)."""
    white = torch.ones(3, 4, 4, dtype=torch.float64)
    u0, u1, v0, v1 = 3.25, 12.75, 2.5, 9.0  # on quarter-pixel boundaries: exact for n = 4, 8
    img, cov, _ = render_planes([_front_plane(white, u0, u1, v0, v1)], _camera_at(), samples=samples)
    exact = np.outer(_box_coverage(v0, v1, SIZE), _box_coverage(u0, u1, SIZE))
    np.testing.assert_allclose(cov[0].numpy(), exact, atol=1e-12)
    np.testing.assert_allclose(img.numpy(), np.broadcast_to(exact, (3, SIZE, SIZE)), atol=1e-12)
    # an arbitrary edge position: error bounded by one sub-sample row/column per edge
    u0, u1 = 3.1, 12.93
    _, cov, _ = render_planes([_front_plane(white, u0, u1, v0, v1)], _camera_at(), samples=samples)
    exact = np.outer(_box_coverage(v0, v1, SIZE), _box_coverage(u0, u1, SIZE))
    assert np.abs(cov[0].numpy() - exact).max() <= 1.0 / samples + 1e-9


@pytest.mark.parametrize("width, height", [(8, 8), (10, 6)])
def test_render_planes_covers_the_projected_pixels_rows_down_columns_across(width, height):
    """An off-centre plane covering the left columns and some rows of the image covers exactly the pixels
    its edges project onto (analytic: the pinhole projection of its corners), in row-major ``[1, H, W]``
    layout -- on a square image too, where a transposed sample grid would still have the right shape."""
    cam = _pinhole(width, height, f=4.0)
    cols, rows = (0, 3), (1, height - 1 - 1)  # left three columns; rows 1 .. H-3 (not symmetric about the centre)
    image, coverage, depth = render_planes([_plane_over_pixels(cam, 2.0, cols, rows)], cam, samples=4,
                                           background=(1.0, 0.0, 0.0))
    expect = torch.zeros(1, height, width, dtype=F64)
    expect[0, rows[0]:rows[1], cols[0]:cols[1]] = 1.0
    assert coverage.shape == (1, height, width)
    assert torch.equal(coverage, expect)
    assert torch.allclose(depth, 2.0 * expect, atol=1e-12)  # the plane's camera z where covered, 0 elsewhere
    grey, red = torch.full((3, 1, 1), 0.5, dtype=F64), torch.tensor([1.0, 0.0, 0.0], dtype=F64)[:, None, None]
    assert torch.allclose(image, expect * grey + (1 - expect) * red, atol=1e-12)


def test_plane_seen_by_a_translated_camera_covers_its_projected_rectangle():
    """A 1 x 1 fronto-parallel plane at depth 4 seen by a camera whose world-to-camera translation is
    (0.3, 0, 0): in camera space it spans x in [-0.2, 0.8], y in [-0.5, 0.5], so with f = 40, c = 16 it
    covers pixels u in [14, 24), v in [11, 21) exactly (edges on pixel boundaries): 100 pixels, depth 4."""
    plane = TexturedPlane("p", torch.tensor([0.0, 0.0, 4.0]), torch.tensor([0.5, 0.0, 0.0]),
                          torch.tensor([0.0, 0.5, 0.0]), torch.full((3, 8, 8), 0.5))
    cam = _pinhole(32, 32, 40.0, (0.3, 0.0, 0.0))
    image, coverage, depth = render_planes([plane], cam, samples=4)
    want = torch.zeros(1, 32, 32, dtype=torch.float64)
    want[:, 11:21, 14:24] = 1.0
    assert torch.equal(coverage, want)
    assert torch.allclose(depth[want > 0], torch.full((100,), 4.0, dtype=torch.float64), atol=1e-12)
    assert float(depth[want == 0].abs().max()) == 0.0


def test_the_nearest_plane_wins_over_the_background():
    cam = _camera_at(4.0, 8, 90.0)
    # camera at z = 4 looking at -z, f = 4, c = 4: a plane at z = 0 spanning x, y in [-2, 2] covers
    # u = 4 + 4 x / 4 in [2, 6]; a nearer plane at z = 2 spanning [-0.5, 0.5] covers u in [3, 5]
    far = _flat((1.0, 0.0, 0.0), (0.0, 0.0, 0.0), 2.0, 2.0)
    near = _flat((0.0, 0.0, 1.0), (0.0, 0.0, 2.0), 0.5, 0.5)
    for planes in ([far, near], [near, far]):  # the nearest wins whatever the list order
        img, cov, depth = render_planes(planes, cam, samples=2, background=(0.0, 0.5, 0.0))
        assert img.shape == (3, 8, 8) and img.dtype == F64
        np.testing.assert_allclose(img[:, 3, 3].numpy(), [0.0, 0.0, 1.0], atol=1e-12)
        np.testing.assert_allclose(img[:, 2, 2].numpy(), [1.0, 0.0, 0.0], atol=1e-12)
        np.testing.assert_allclose(img[:, 0, 0].numpy(), [0.0, 0.5, 0.0], atol=1e-12)  # background
        assert float(cov[0, 0, 0]) == 0.0 and float(depth[0, 0, 0]) == 0.0
        assert float(cov[0, 2, 2]) == 1.0
        assert abs(float(depth[0, 2, 2]) - 4.0) < 1e-12 and abs(float(depth[0, 3, 3]) - 2.0) < 1e-12
    # the default background is black
    img, _, _ = render_planes([near], cam, samples=1)
    assert float(img[:, 0, 0].abs().max()) == 0.0


def test_render_partial_pixel_depth_and_behind_camera():
    cam = _camera_at(4.0, 8, 90.0)
    # plane at z = 0 covering u in [2, 4.5] x v in [2, 6]: column 4 is half covered; its mean depth over
    # the covered sub-samples stays 4 (not 2: the uncovered ones do not count)
    half = _flat((1.0, 1.0, 1.0), (-0.75, 0.0, 0.0), 1.25, 2.0)
    img, cov, depth = render_planes([half], cam, samples=4)
    np.testing.assert_allclose(cov[0, 3, :].numpy(), [0, 0, 1, 1, 0.5, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(img[0, 3, :].numpy(), [0, 0, 1, 1, 0.5, 0, 0, 0], atol=1e-12)
    assert abs(float(depth[0, 3, 4]) - 4.0) < 1e-12
    # a floor reaching behind the camera (corners not in front: no window): y = -1 from z = -50 to 50;
    # a ray hits it iff it points down (v > 4), so the lower half is covered and the upper is not
    floor = TexturedPlane("floor", _t(0, -1, 0), _t(50, 0, 0), _t(0, 0, 50), torch.ones(3, 2, 2, dtype=F64))
    _, cov, depth = render_planes([floor], cam, samples=2)
    np.testing.assert_allclose(cov[0].numpy(), np.repeat([[0.0] * 4 + [1.0] * 4], 8, axis=0).T, atol=1e-12)
    # depth of a floor pixel: t = 1 / dy with dy = (v - 4) / 4; sub-sample rows v = 4.25, 4.75 -> t = 16, 16/3
    assert abs(float(depth[0, 4, 3]) - (16 + 16 / 3) / 2) < 1e-9
    # a plane entirely outside the view contributes nothing
    off = _flat((1.0, 1.0, 1.0), (30.0, 0.0, 0.0), 1.0, 1.0)
    _, cov, _ = render_planes([off], cam, samples=1)
    assert float(cov.max()) == 0.0
    # a plane behind the camera is not seen
    behind = _flat((1.0, 1.0, 1.0), (0.0, 0.0, 6.0), 3.0, 3.0)
    _, cov, _ = render_planes([behind], cam, samples=1)
    assert float(cov.max()) == 0.0


def test_render_clamps_to_the_unit_range():
    cam = _camera_at(4.0, 8, 90.0)
    near = _flat((0.25, 0.25, 0.25), (0.0, 0.0, 2.0), 0.5, 0.5)
    img, _, _ = render_planes([near], cam, samples=1, background=(2.0, -1.0, 0.5))  # documented: image in [0, 1]
    np.testing.assert_allclose(img[:, 0, 0].numpy(), [1.0, 0.0, 0.5], atol=0)
    np.testing.assert_allclose(img[:, 4, 4].numpy(), [0.25, 0.25, 0.25], atol=1e-12)


def test_samples_must_be_positive():
    with pytest.raises(InputValueError, match="samples"):
        render_planes([], _camera_at(), samples=0)


def test_texture_filtering_matches_box_integral():
    """Pixels of a minified photograph equal the box-filter integral of the bilinear texture
    (independent brute force with 32 x 32 point samples per pixel, float64 numpy)."""
    tex = load_texture("astronaut")[:, ::2, ::2].contiguous()  # 256 x 256, about 25 texels per pixel
    size = 24
    u0, u1, v0, v1 = 7.0, 17.0, 6.0, 16.0
    cam, plane = _camera_at(size=size), _front_plane(tex, u0, u1, v0, v1, size)
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


@pytest.mark.parametrize("yaw, tex_hw, samples", [(0.0, (8, 32), 1), (0.0, (8, 24), 1), (50.0, (16, 20), 1),
                                                  (-35.0, (40, 12), 2)])
def test_mip_level_follows_the_sub_sample_footprint(yaw, tex_hw, samples):
    """The lod is log2 of the larger texel footprint of one sub-sample step in u or v (at least 1),
    checked against finite differences of the ray-plane hit (front plane 4 x 2 world units, 32 x 8
    texels, camera 4 units away with f = 4: a pixel step moves 1 unit, i.e. 8 and 4 texels -> lod 3;
    a min instead of the max would give 2)."""
    cam = look_at((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), size=8, fov_deg=90.0)
    y = math.radians(yaw)
    plane = _level_coded(TexturedPlane("p", _t(0, 0, 0), _t(2 * math.cos(y), 0, -2 * math.sin(y)), _t(0, -1, 0),
                                       torch.zeros(3, *tex_hw, dtype=F64)))
    img, cov, _ = render_planes([plane], cam, samples=samples)
    n, eps = samples, 1e-4
    for row, col in ((4, 4), (3, 4), (4, 3)):
        vals = []
        for i in range(n):
            for j in range(n):
                u, v = col + (j + 0.5) / n, row + (i + 0.5) / n
                fu = np.linalg.norm(_texel(plane, cam, u + eps, v) - _texel(plane, cam, u - eps, v)) / (2 * eps) / n
                fv = np.linalg.norm(_texel(plane, cam, u, v + eps) - _texel(plane, cam, u, v - eps)) / (2 * eps) / n
                vals.append(math.log2(max(fu, fv, 1.0)) / 10)
        assert float(cov[0, row, col]) == 1.0
        assert abs(float(img[0, row, col]) - float(np.mean(vals))) < 1e-6, (row, col)
    if yaw == 0.0 and tex_hw == (8, 32):
        assert abs(float(img[0, 4, 4]) - 0.3) < 1e-9  # footprints 32/4 = 8 and 8/2 = 4 texels
