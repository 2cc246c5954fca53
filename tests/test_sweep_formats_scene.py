"""The built-in scene's pieces pinned by hand: camera poses and intrinsics derived on paper, the
diorama's geometry, plane refusals and texture lookups against float64 brute force, the mip
filter's weights, the ground-truth cache's key and split, and every documented default."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

pytest.importorskip("skimage")

from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError
from controlgs_adapter.formats.safetensors import save_tensors
from controlgs_adapter.scene import (TEXTURES, TexturedPlane, arc_cameras, builtin_backbone_dir, default_cache_dir,
                                     diorama_planes, load_builtin_backbone, load_builtin_scene, load_texture, look_at,
                                     mip_pyramid, plane_points, render_planes)

F64 = torch.float64


def _t(*v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


# ---------------------------------------------------------------------------------------------- cameras

def test_look_at_pose_and_intrinsics_by_hand():
    # eye (0, 0, 5) -> origin, up y: z = (0, 0, -1); x = z x up = (1, 0, 0); y = z x x = (0, -1, 0);
    # t = -R e = (0, 0, 5); fov 90 deg: f = size / (2 tan 45) = size / 2 = 5, c = 5
    cam = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), size=10, fov_deg=90.0)
    want = torch.tensor([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 5], [0, 0, 0, 1]], dtype=torch.float32)
    torch.testing.assert_close(cam.world_to_camera, want, atol=1e-6, rtol=0)
    torch.testing.assert_close(cam.intrinsics, torch.tensor([[5.0, 0, 5], [0, 5, 5], [0, 0, 1]]), atol=1e-6, rtol=0)
    assert (cam.width, cam.height) == (10, 10)
    assert cam.world_to_camera.dtype == torch.float32
    # eye (3, 0, 0) -> origin: z = (-1, 0, 0), x = (0, 0, -1), y = (0, -1, 0), t = -R e = (0, 0, 3)
    cam = look_at((3.0, 0.0, 0.0), (0.0, 0.0, 0.0), size=8, fov_deg=60.0)
    want = torch.tensor([[0, 0, -1, 0], [0, -1, 0, 0], [-1, 0, 0, 3], [0, 0, 0, 1]], dtype=torch.float32)
    torch.testing.assert_close(cam.world_to_camera, want, atol=1e-6, rtol=0)
    f = 8 / (2 * math.tan(math.radians(30.0)))  # 6.9282
    torch.testing.assert_close(cam.intrinsics, torch.tensor([[f, 0, 4], [0, f, 4], [0, 0, 1]]), atol=1e-5, rtol=0)
    # an eye off the axes: its centre comes back, the target projects to the image centre
    cam = look_at((1.0, 2.0, 3.0), (0.5, -1.0, 0.25), size=12, fov_deg=40.0)
    torch.testing.assert_close(cam.center, torch.tensor([1.0, 2.0, 3.0]), atol=1e-5, rtol=0)
    p = cam.world_to_camera.double() @ _t(0.5, -1.0, 0.25, 1.0)
    k = cam.intrinsics.double()
    assert abs(float(k[0, 0] * p[0] / p[2] + k[0, 2]) - 6.0) < 1e-4 and abs(float(k[1, 1] * p[1] / p[2] + k[1, 2]) - 6.0) < 1e-4
    # a point above the target (world +y) is above the centre in the image (smaller v)
    cam = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), size=10, fov_deg=90.0)
    p = cam.world_to_camera.double() @ _t(1.0, 1.0, 0.0, 1.0)  # -> camera (1, -1, 5): u = 6, v = 4
    assert abs(float(5 * p[0] / p[2] + 5) - 6.0) < 1e-6 and abs(float(5 * p[1] / p[2] + 5) - 4.0) < 1e-6


def test_look_at_refusals():
    with pytest.raises(InputValueError, match="eye and target must differ"):
        look_at((1.0, 1.0, 1.0), (1.0, 1.0, 1.0), size=8, fov_deg=50.0)
    with pytest.raises(InputValueError, match="parallel to up"):
        look_at((0.0, 3.0, 0.0), (0.0, 0.0, 0.0), size=8, fov_deg=50.0)
    # a custom up: looking down y is fine when up is z
    cam = look_at((0.0, 3.0, 0.0), (0.0, 0.0, 0.0), size=8, fov_deg=50.0, up=(0.0, 0.0, 1.0))
    torch.testing.assert_close(cam.center, torch.tensor([0.0, 3.0, 0.0]), atol=1e-6, rtol=0)


def _arc_eye(s: float) -> tuple[float, float, float]:
    """The documented defaults by hand: azimuth in [-32, 32] deg, elevation 8..24 deg with five
    half-periods, radius 5.2 -> 4.2 with three half-periods, target (0, 0.35, 0)."""
    az = math.radians(-32.0 + 64.0 * s)
    el = math.radians(8.0 + 16.0 * (0.5 - 0.5 * math.cos(5.0 * math.pi * s)))
    r = 5.2 - 1.0 * (0.5 - 0.5 * math.cos(3.0 * math.pi * s))
    return (r * math.cos(el) * math.sin(az), 0.35 + r * math.sin(el), r * math.cos(el) * math.cos(az))


def test_arc_cameras_defaults_by_hand():
    cams = arc_cameras(3, size=20)
    # s = 0: az -32, el 8, r 5.2; s = 0.5: az 0, el 16, r 4.7; s = 1: az 32, el 24, r 4.2
    eyes = [(5.2 * math.cos(math.radians(8)) * math.sin(math.radians(-32)), 0.35 + 5.2 * math.sin(math.radians(8)),
             5.2 * math.cos(math.radians(8)) * math.cos(math.radians(32))),
            (0.0, 0.35 + 4.7 * math.sin(math.radians(16)), 4.7 * math.cos(math.radians(16))),
            (4.2 * math.cos(math.radians(24)) * math.sin(math.radians(32)), 0.35 + 4.2 * math.sin(math.radians(24)),
             4.2 * math.cos(math.radians(24)) * math.cos(math.radians(32)))]
    for cam, eye, s in zip(cams, eyes, (0.0, 0.5, 1.0)):
        torch.testing.assert_close(cam.center.double(), _t(*eye), atol=2e-5, rtol=0)
        torch.testing.assert_close(cam.center.double(), _t(*_arc_eye(s)), atol=2e-5, rtol=0)
        # default fov 50 deg: f = 20 / (2 tan 25) = 21.445
        assert abs(float(cam.intrinsics[0, 0]) - 20 / (2 * math.tan(math.radians(25.0)))) < 1e-4
        assert abs(float(cam.intrinsics[1, 1]) - 21.4451) < 1e-3
        # every camera looks at the target (0, 0.35, 0): it projects to the centre (10, 10)
        p = cam.world_to_camera.double() @ _t(0.0, 0.35, 0.0, 1.0)
        k = cam.intrinsics.double()
        assert abs(float(k[0, 0] * p[0] / p[2] + k[0, 2]) - 10) < 1e-3 and abs(float(k[1, 1] * p[1] / p[2] + k[1, 2]) - 10) < 1e-3
    one = arc_cameras(1, size=8)  # one camera: s = 0
    torch.testing.assert_close(one[0].center.double(), _t(*_arc_eye(0.0)), atol=2e-5, rtol=0)
    five = arc_cameras(5, size=8)
    for i, cam in enumerate(five):
        torch.testing.assert_close(cam.center.double(), _t(*_arc_eye(i / 4)), atol=2e-5, rtol=0)


def test_arc_cameras_options_and_refusal():
    cams = arc_cameras(2, size=10, fov_deg=90.0, radius=(2.0, 3.0), azimuth_deg=45.0, elevation_deg=(0.0, 30.0),
                       target=(1.0, 0.0, -1.0))
    # s = 0: az -45, wobble 0 -> el 0, r = 3 - 1 * 0 = 3; s = 1: az 45, wobble 1 -> el 30, r = 3 - 1 * 1 = 2
    e0 = (1.0 + 3.0 * math.sin(math.radians(-45)), 0.0, -1.0 + 3.0 * math.cos(math.radians(45)))
    e1 = (1.0 + 2.0 * math.cos(math.radians(30)) * math.sin(math.radians(45)), 2.0 * math.sin(math.radians(30)),
          -1.0 + 2.0 * math.cos(math.radians(30)) * math.cos(math.radians(45)))
    torch.testing.assert_close(cams[0].center.double(), _t(*e0), atol=2e-5, rtol=0)
    torch.testing.assert_close(cams[1].center.double(), _t(*e1), atol=2e-5, rtol=0)
    assert abs(float(cams[0].intrinsics[0, 0]) - 5.0) < 1e-5  # fov 90: f = size / 2
    for bad in (0, -2):
        with pytest.raises(InputValueError, match=f"count must be >= 1, got {bad}"):
            arc_cameras(bad, size=8)


# ---------------------------------------------------------------------------------------------- planes

# name, texture, centre, width, height, yaw, pitch, repeat: the diorama as documented in docs/scene.md
_AR = [("rocket", "rocket", (-1.15, 1.0, -1.0), 1.8, 1.2, 20.0, 0.0, (1, 1)),
       ("coffee", "coffee", (1.15, 0.9, -1.15), 1.8, 1.2, -18.0, 0.0, (1, 1)),
       ("brick-panel", "brick", (0.0, 0.45, -0.35), 0.8, 1.5, 6.0, 0.0, (1, 1)),
       ("astronaut", "astronaut", (-0.8, 0.25, 0.45), 1.1, 1.1, 28.0, 0.0, (1, 1)),
       ("chelsea", "chelsea", (0.85, 0.05, 0.6), 1.35, 0.9, -32.0, -12.0, (1, 1)),
       ("gravel-ramp", "gravel", (-0.1, -0.3, 1.1), 1.0, 0.6, 0.0, -60.0, (1, 1)),
       ("grass-patch", "grass", (0.0, -0.55, -0.1), 3.4, 2.8, 0.0, -90.0, (1, 1))]
_VR = [("wall", "brick", (0.0, 3.0, -3.2), 26.0, 12.0, 0.0, 0.0, (6, 3)),
       ("floor", "gravel", (0.0, -0.62, 1.0), 26.0, 20.0, 0.0, -90.0, (8, 6))]


def _axes(width: float, height: float, yaw: float, pitch: float) -> tuple[torch.Tensor, torch.Tensor]:
    """right = R_y (w/2, 0, 0) = w/2 (cos y, 0, -sin y); down = R_y R_x (0, -h/2, 0)
    = -h/2 (sin y sin p, cos p, cos y sin p) (worked out on paper)."""
    y, p = math.radians(yaw), math.radians(pitch)
    right = _t(width / 2 * math.cos(y), 0.0, -width / 2 * math.sin(y))
    down = _t(-height / 2 * math.sin(y) * math.sin(p), -height / 2 * math.cos(p), -height / 2 * math.cos(y) * math.sin(p))
    return right, down


@pytest.mark.parametrize("variant", ["ar", "vr"])
def test_diorama_geometry_by_hand(variant):
    planes = diorama_planes(variant)
    table = _AR + (_VR if variant == "vr" else [])
    assert [p.name for p in planes] == [row[0] for row in table]
    for p, (name, tex, center, w, h, yaw, pitch, rep) in zip(planes, table):
        right, down = _axes(w, h, yaw, pitch)
        torch.testing.assert_close(p.center, _t(*center), atol=1e-12, rtol=0, msg=name)
        torch.testing.assert_close(p.right, right, atol=1e-12, rtol=0, msg=name)
        torch.testing.assert_close(p.down, down, atol=1e-12, rtol=0, msg=name)
        assert p.repeat == rep, name
        assert torch.equal(p.texture, load_texture(tex)), name
    # a plane facing the viewer on +z has normal right x down = -z (away from the viewer)
    torch.testing.assert_close(diorama_planes("ar")[2].normal,
                               _t(-math.sin(math.radians(6)), 0.0, -math.cos(math.radians(6))), atol=1e-12, rtol=0)
    with pytest.raises(InputValueError, match=r"variant must be one of \('ar', 'vr'\), got 'xr'"):
        diorama_planes("xr")


def test_make_defaults_face_plus_z_untiled():
    p = TexturedPlane.make("p", "brick", (1.0, 2.0, 3.0), 2.0, 4.0)
    torch.testing.assert_close(p.right, _t(1.0, 0.0, 0.0), atol=1e-15, rtol=0)
    torch.testing.assert_close(p.down, _t(0.0, -2.0, 0.0), atol=1e-15, rtol=0)
    torch.testing.assert_close(p.normal, _t(0.0, 0.0, -1.0), atol=1e-15, rtol=0)
    assert p.repeat == (1, 1)


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


def _bilinear(tex: np.ndarray, a: float, b: float) -> np.ndarray:
    """Bilinear texel lookup at plane coordinates a, b in [-1, 1] (pixel centres at i + 0.5, edges clamped)."""
    h, w = tex.shape[1:]
    x, y = np.clip((a + 1) / 2 * w - 0.5, 0, w - 1), np.clip((b + 1) / 2 * h - 0.5, 0, h - 1)
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    return (tex[:, y0, x0] * (1 - fx) * (1 - fy) + tex[:, y0, x1] * fx * (1 - fy)
            + tex[:, y1, x0] * (1 - fx) * fy + tex[:, y1, x1] * fx * fy)


def test_sample_bilinear_lod_blend_and_clamp_by_hand():
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


def test_mip_pyramid_uses_the_triangle_filter():
    # 1 x 4 row [1, 0, 0, 0] -> 1 x 2: the antialiased bilinear (triangle) filter at scale 2 weighs input
    # pixels at distance 0.5, 0.5, 1.5 from output 0's centre by 1 - d/2 = 0.75, 0.75, 0.25 (renormalised:
    # 1.75), so output 0 = 0.75 / 1.75 = 3/7; a plain bilinear resize would give 0.5
    row = torch.tensor([[[1.0, 0.0, 0.0, 0.0]]], dtype=F64).expand(3, 1, 4)
    levels = mip_pyramid(row)
    assert [tuple(lvl.shape) for lvl in levels] == [(3, 1, 4), (3, 1, 2), (3, 1, 1)]
    np.testing.assert_allclose(levels[1][0, 0].numpy(), [3 / 7, 0.0], atol=1e-12)
    assert mip_pyramid(torch.ones(3, 1, 1, dtype=F64))[0].shape == (3, 1, 1) and len(mip_pyramid(torch.ones(3, 1, 1))) == 1


def test_plane_points_grid_and_colour_by_hand():
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


# --------------------------------------------------------------------------------------------- rendering

def _cam(size: int = 8):
    return look_at((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), size=size, fov_deg=90.0)  # f = size / 2


def _flat(color, center, half_w, half_h, w_tex=2):
    tex = torch.tensor(color, dtype=F64)[:, None, None].expand(3, 2, w_tex).clone()
    return TexturedPlane("p", _t(*center), _t(half_w, 0, 0), _t(0, -half_h, 0), tex)


def test_render_nearest_plane_background_and_depth_by_hand():
    cam = _cam()
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
    cam = _cam()
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


# ------------------------------------------------------------------------------------------- textures

def test_textures_are_the_skimage_photographs_tinted():
    import skimage.data

    for name in ("astronaut", "chelsea"):
        t = load_texture(name)
        ref = skimage.data.__dict__[name]().astype(np.float64) / 255.0
        assert t.dtype == F64
        np.testing.assert_array_equal(t.numpy(), ref.transpose(2, 0, 1))
    tints = {"brick": (0.92, 0.55, 0.42), "grass": (0.55, 0.85, 0.35), "gravel": (0.85, 0.80, 0.70)}
    for name, tint in tints.items():
        assert TEXTURES[name].tint == tint
        t = load_texture(name)
        grey = skimage.data.__dict__[name]().astype(np.float64) / 255.0
        np.testing.assert_allclose(t.numpy(), grey[None] * np.asarray(tint)[:, None, None], rtol=0, atol=1e-15)
    assert [n for n, i in TEXTURES.items() if i.tint is None] == ["astronaut", "coffee", "chelsea", "rocket"]
    # a fresh copy every time: editing one does not change the next
    t = load_texture("coffee")
    t.zero_()
    assert float(load_texture("coffee").max()) > 0.5
    with pytest.raises(InputValueError, match=r"texture must be one of \['astronaut'.*got 'lena'"):
        load_texture("lena")


# -------------------------------------------------------------------------------------- the whole scene

def _key_name(variant: str, resolution: int, views: int, samples: int, fov: float) -> str:
    """The documented cache key: every argument and the scene version, in this order."""
    return f"builtin-variant{variant}-resolution{resolution}-views{views}-samples{samples}-fov_deg{fov}-scene_version1.safetensors"


def _plant(folder, name: str, n: int, res: int, key: dict) -> torch.Tensor:
    """A cache file holding image i = i / 100 everywhere (not a rendering: a read of it is recognisable)."""
    images = torch.arange(n, dtype=torch.float32).div(100)[:, None, None, None].expand(n, 3, res, res).contiguous()
    save_tensors(folder / name, {"images": images}, {"key": key}, kind="controlgs_builtin_scene_images", format_version=1)
    return images


def test_load_builtin_scene_defaults_read_through_the_cache(tmp_path):
    # defaults: variant ar, resolution 128, views 32, test_every 8, samples 4, fov 50
    key = {"variant": "ar", "resolution": 128, "views": 32, "samples": 4, "fov_deg": 50.0, "scene_version": 1}
    images = _plant(tmp_path, _key_name("ar", 128, 32, 4, 50.0), 32, 128, key)
    s = load_builtin_scene(cache=tmp_path)
    assert len(list(tmp_path.iterdir())) == 1  # read, not rendered and written again
    # test split: i % 8 == 0 -> views 0, 8, 16, 24; train: the other 28
    assert torch.equal(s.test_images, images[[0, 8, 16, 24]])
    assert torch.equal(s.train_images, images[[i for i in range(32) if i % 8]])
    assert (s.variant, s.resolution, s.name) == ("ar", 128, "builtin-ar")
    cams = arc_cameras(32, size=128, fov_deg=50.0)
    torch.testing.assert_close(s.test_cameras[1].world_to_camera, cams[8].world_to_camera, atol=0, rtol=0)
    torch.testing.assert_close(s.train_cameras[0].world_to_camera, cams[1].world_to_camera, atol=0, rtol=0)
    assert len(s.train_cameras) == 28 and len(s.test_cameras) == 4
    assert torch.equal(s.background, torch.zeros(3)) and s.background.dtype == torch.float32
    assert [p.name for p in s.planes] == [row[0] for row in _AR]
    assert s.data.format == "builtin" and s.data.source == "builtin-ar"
    assert [f.name for f in s.data.splits["test"]] == [f"builtin-ar/test/{i:04d}" for i in range(4)]
    assert [f.name for f in s.data.splits["train"]][:2] == ["builtin-ar/train/0000", "builtin-ar/train/0001"]
    assert torch.equal(s.data.splits["test"][2].source, images[16]) and s.data.splits["train"][7].source is not None
    assert torch.equal(s.data.splits["train"][7].source, images[9])  # train view 7 is arc view 9 (0 and 8 held out)
    assert torch.equal(s.data.background, torch.zeros(3))
    v = s.views("test")
    assert len(v) == 4
    # points(): default spacing 0.05, float32, the planes' grids concatenated
    xyz, rgb = s.points()
    want = [plane_points(p, 0.05) for p in s.planes]
    assert xyz.dtype == torch.float32 and torch.equal(xyz, torch.cat([w[0] for w in want]).float())
    assert torch.equal(rgb, torch.cat([w[1] for w in want]).float())


def test_scene_cache_key_options_and_stale_files(tmp_path, monkeypatch):
    key = {"variant": "vr", "resolution": 16, "views": 6, "samples": 1, "fov_deg": 30.0, "scene_version": 1}
    name = _key_name("vr", 16, 6, 1, 30.0)
    images = _plant(tmp_path, name, 6, 16, key)
    s = load_builtin_scene("vr", 16, views=6, test_every=3, samples=1, fov_deg=30.0, cache=str(tmp_path))
    assert torch.equal(s.test_images, images[[0, 3]]) and torch.equal(s.train_images, images[[1, 2, 4, 5]])
    assert abs(float(s.train_cameras[0].intrinsics[0, 0]) - 8 / math.tan(math.radians(15))) < 1e-3
    # a file whose header key differs is not trusted: rendered again (and rewritten)
    _plant(tmp_path, name, 6, 16, {**key, "samples": 2})
    s = load_builtin_scene("vr", 16, views=6, test_every=3, samples=1, fov_deg=30.0, cache=tmp_path)
    assert float(s.train_images.max()) > 0.1 and not torch.equal(s.train_images, images[[1, 2, 4, 5]])
    fresh = load_builtin_scene("vr", 16, views=6, test_every=3, samples=1, fov_deg=30.0)
    assert torch.equal(s.train_images, fresh.train_images)
    again = load_builtin_scene("vr", 16, views=6, test_every=3, samples=1, fov_deg=30.0, cache=tmp_path)  # rewritten
    assert torch.equal(again.test_images, fresh.test_images)
    # a file of the wrong image count is not trusted either
    _plant(tmp_path, name, 5, 16, key)
    s = load_builtin_scene("vr", 16, views=6, test_every=3, samples=1, fov_deg=30.0, cache=tmp_path)
    assert torch.equal(s.test_images, fresh.test_images)
    # cache=True: $XDG_CACHE_HOME/controlgs-adapter/scene; without it ~/.cache/...
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "controlgs-adapter" / "scene"
    (tmp_path / "xdg" / "controlgs-adapter" / "scene").mkdir(parents=True)
    planted = _plant(tmp_path / "xdg" / "controlgs-adapter" / "scene", name, 6, 16, key)
    s = load_builtin_scene("vr", 16, views=6, test_every=3, samples=1, fov_deg=30.0, cache=True)
    assert torch.equal(s.test_images, planted[[0, 3]])
    # cache=False / None: never read
    s = load_builtin_scene("vr", 16, views=6, test_every=3, samples=1, fov_deg=30.0, cache=False)
    assert torch.equal(s.test_images, fresh.test_images)
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "controlgs-adapter" / "scene"


def test_load_builtin_scene_bounds():
    s = load_builtin_scene("ar", 16, views=2, test_every=2, samples=1)  # the smallest accepted
    assert s.train_images.shape == (1, 3, 16, 16) and s.test_images.shape == (1, 3, 16, 16)
    with pytest.raises(InputValueError, match="resolution must be >= 16 pixels, got 15"):
        load_builtin_scene("ar", 15, views=2, test_every=2, samples=1)
    with pytest.raises(InputValueError, match="need views >= test_every >= 2, got views=4, test_every=1"):
        load_builtin_scene("ar", 16, views=4, test_every=1, samples=1)
    with pytest.raises(InputValueError, match="need views >= test_every >= 2, got views=2, test_every=3"):
        load_builtin_scene("ar", 16, views=2, test_every=3, samples=1)
    with pytest.raises(InputValueError, match="variant must be one of"):
        load_builtin_scene("xr", 16, views=2, test_every=2, samples=1)


def test_builtin_backbone_folders():
    from controlgs_adapter.scene import backbone as sb

    assert builtin_backbone_dir() == sb._DATA / "ar" and builtin_backbone_dir("vr") == sb._DATA / "vr"
    assert sb._DATA.parts[-3:] == ("controlgs_adapter", "data", "builtin_scene")
    with pytest.raises(InputValueError, match=r"variant must be one of \('ar', 'vr'\), got 'xr'"):
        builtin_backbone_dir("xr")


def test_load_builtin_backbone_missing_names_the_bake_command(tmp_path, monkeypatch):
    from controlgs_adapter.scene import backbone as sb

    monkeypatch.setattr(sb, "_DATA", tmp_path)  # an installation without the baked files
    with pytest.raises(FileFormatError, match=r"the built-in 'vr' backbone is not baked.*--variant vr --out "):
        load_builtin_backbone("vr")


def test_build_builtin_backbone_records_its_arguments_and_scores(tmp_path, monkeypatch):
    import json

    from controlgs_adapter.backends.scaffold_io import load_scaffold_dir
    from controlgs_adapter.metrics import psnr
    from controlgs_adapter.scene import build_builtin_backbone

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # the scene's ground truth is cached here
    out = build_builtin_backbone("ar", out=tmp_path / "bb", resolution=16, iterations=2, max_anchors=40, n_offsets=2,
                                 feat_dim=8, point_spacing=0.3, seed=1, progress=False)
    assert out == tmp_path / "bb" and (out / "point_cloud" / "iteration_2").is_dir()
    assert len(list((tmp_path / "cache" / "controlgs-adapter" / "scene").iterdir())) == 1  # cache=True
    info = json.loads((out / "build.json").read_text())
    assert {k: info[k] for k in ("variant", "resolution", "iterations", "max_anchors", "n_offsets", "feat_dim",
                                 "point_spacing", "seed")} == {"variant": "ar", "resolution": 16, "iterations": 2,
                                                               "max_anchors": 40, "n_offsets": 2, "feat_dim": 8,
                                                               "point_spacing": 0.3, "seed": 1}
    model = load_scaffold_dir(out).eval()
    assert info["anchors"] == model.num_anchors <= 40
    # 32 views, every 8th held out: 4 test views, each scored on the saved model's render
    scene = load_builtin_scene("ar", 16, cache=True)
    assert len(info["test_psnr"]) == len(info["test_ssim"]) == 4
    with torch.no_grad():
        want = [float(psnr(model.render(c, None, scene.background).color.clamp(0, 1), g))
                for c, g in zip(scene.test_cameras, scene.test_images)]
    np.testing.assert_allclose(info["test_psnr"], want, atol=1e-3)
    assert abs(info["test_psnr_mean"] - sum(want) / 4) < 1e-3
    assert abs(info["test_ssim_mean"] - sum(info["test_ssim"]) / 4) < 1e-12
    assert all(0.0 < s <= 1.0 for s in info["test_ssim"]) and info["train_seconds"] >= 0.0


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
        assert abs(float(img[0, 4, 4]) - 0.3) < 1e-9  # by hand: footprints 32/4 = 8 and 8/2 = 4 texels


def test_render_clamps_to_the_unit_range_and_baked_backbone_is_in_eval_mode():
    cam = _cam()
    near = _flat((0.25, 0.25, 0.25), (0.0, 0.0, 2.0), 0.5, 0.5)
    img, _, _ = render_planes([near], cam, samples=1, background=(2.0, -1.0, 0.5))  # documented: image in [0, 1]
    np.testing.assert_allclose(img[:, 0, 0].numpy(), [1.0, 0.0, 0.5], atol=0)
    np.testing.assert_allclose(img[:, 4, 4].numpy(), [0.25, 0.25, 0.25], atol=1e-12)
    model = load_builtin_backbone("ar")
    assert not model.training and all(not m.training for m in model.modules())
