"""Tests of ``controlgs_adapter.scene.diorama``: the built-in scene's planes, cameras, split and ground truth, its
defaults, bounds and the on-disk cache of the rendered ground truth."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.formats.safetensors import save_tensors
from controlgs_adapter.scene import default_cache_dir, diorama_planes, load_builtin_scene, load_texture, render_planes
from controlgs_adapter.scene.cameras import arc_cameras
from controlgs_adapter.scene.planes import plane_points

pytest.importorskip("skimage")  # the built-in textures

F64 = torch.float64


def _t(*v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


#: name, texture, centre, width, height, yaw, pitch, repeat of each plane (docs/reference/builtin-scene.md)
_AR = [("rocket", "rocket", (-1.15, 1.0, -1.0), 1.8, 1.2, 20.0, 0.0, (1, 1)),
       ("coffee", "coffee", (1.15, 0.9, -1.15), 1.8, 1.2, -18.0, 0.0, (1, 1)),
       ("brick-panel", "brick", (0.0, 0.45, -0.35), 0.8, 1.5, 6.0, 0.0, (1, 1)),
       ("astronaut", "astronaut", (-0.8, 0.25, 0.45), 1.1, 1.1, 28.0, 0.0, (1, 1)),
       ("chelsea", "chelsea", (0.85, 0.05, 0.6), 1.35, 0.9, -32.0, -12.0, (1, 1)),
       ("gravel-ramp", "gravel", (-0.1, -0.3, 1.1), 1.0, 0.6, 0.0, -60.0, (1, 1)),
       ("grass-patch", "grass", (0.0, -0.55, -0.1), 3.4, 2.8, 0.0, -90.0, (1, 1))]
#: the VR variant adds a wall and a floor
_VR = [("wall", "brick", (0.0, 3.0, -3.2), 26.0, 12.0, 0.0, 0.0, (6, 3)),
       ("floor", "gravel", (0.0, -0.62, 1.0), 26.0, 20.0, 0.0, -90.0, (8, 6))]


def _axes(width: float, height: float, yaw: float, pitch: float) -> tuple[torch.Tensor, torch.Tensor]:
    """right = R_y (w/2, 0, 0) = w/2 (cos y, 0, -sin y); down = R_y R_x (0, -h/2, 0)
    = -h/2 (sin y sin p, cos p, cos y sin p) (worked out on paper)."""
    y, p = math.radians(yaw), math.radians(pitch)
    right = _t(width / 2 * math.cos(y), 0.0, -width / 2 * math.sin(y))
    down = _t(-height / 2 * math.sin(y) * math.sin(p), -height / 2 * math.cos(p), -height / 2 * math.cos(y) * math.sin(p))
    return right, down


def _key_name(variant: str, resolution: int, views: int, samples: int, fov: float) -> str:
    """The documented cache key: every argument and the scene version, in this order."""
    return f"builtin-variant{variant}-resolution{resolution}-views{views}-samples{samples}-fov_deg{fov}-scene_version1.safetensors"


def _plant(folder, name: str, n: int, res: int, key: dict) -> torch.Tensor:
    """A cache file holding image i = i / 100 everywhere (not a rendering: a read of it is recognisable)."""
    images = torch.arange(n, dtype=torch.float32).div(100)[:, None, None, None].expand(n, 3, res, res).contiguous()
    save_tensors(folder / name, {"images": images}, {"key": key}, kind="controlgs_builtin_scene_images", format_version=1)
    return images


# ----------------------------------------------------------------------------- the scene

@pytest.mark.parametrize("variant", ["ar", "vr"])
def test_diorama_planes_are_the_documented_geometry(variant):
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


def test_builtin_scene_holds_out_every_test_every_th_arc_camera():
    """views=8, test_every=4: test = arc cameras 0 and 4, train = 1, 2, 3, 5, 6, 7 (disjoint, in order)."""
    scene = load_builtin_scene("ar", 16, views=8, test_every=4, samples=1)
    arc = arc_cameras(8, size=16)
    for got, i in zip(scene.test_cameras, (0, 4), strict=True):
        torch.testing.assert_close(got.world_to_camera.double(), arc[i].world_to_camera.double())
    for got, i in zip(scene.train_cameras, (1, 2, 3, 5, 6, 7), strict=True):
        torch.testing.assert_close(got.world_to_camera.double(), arc[i].world_to_camera.double())


def test_defaults_render_32_views_4x4_samples_fov_50_every_8th_tested():
    scene = load_builtin_scene(resolution=16)  # default variant "ar", views 32, test_every 8, samples 4, fov 50
    assert scene.variant == "ar" and scene.resolution == 16
    assert len(scene.train_cameras) == 28 and len(scene.test_cameras) == 4  # views 0, 8, 16, 24 are tested
    cams = arc_cameras(32, size=16, fov_deg=50.0)
    for got, want in zip(scene.test_cameras, cams[0::8], strict=True):
        torch.testing.assert_close(got.world_to_camera, want.world_to_camera, rtol=0, atol=0)
        torch.testing.assert_close(got.intrinsics, want.intrinsics, rtol=0, atol=0)
    torch.testing.assert_close(scene.train_cameras[0].world_to_camera, cams[1].world_to_camera, rtol=0, atol=0)
    # the ground truth is rendered with 4 x 4 samples over a black background (render_planes' defaults)
    img4 = render_planes(scene.planes, cams[8])[0].float()
    torch.testing.assert_close(scene.test_images[1], img4, rtol=0, atol=1e-6)
    torch.testing.assert_close(render_planes(scene.planes, cams[8], samples=4, background=(0.0, 0.0, 0.0))[0].float(),
                               img4, rtol=0, atol=0)
    assert float((render_planes(scene.planes, cams[8], samples=1)[0].float() - img4).abs().max()) > 1e-3
    # points(): default spacing 0.05 (a coarser spacing gives fewer points)
    n_default = scene.points()[0].shape[0]
    assert n_default == scene.points(0.05)[0].shape[0] > scene.points(0.1)[0].shape[0]


def test_vr_variant_has_no_background():
    s = load_builtin_scene("vr", 16, views=4, test_every=2, samples=1)
    for cam in s.train_cameras + s.test_cameras:
        _, coverage, depth = render_planes(s.planes, cam, samples=1)
        assert float(coverage.min()) == 1.0 and float(depth.min()) > 0.0


def test_load_builtin_scene_bounds():
    s = load_builtin_scene("ar", 16, views=2, test_every=2, samples=1)  # the smallest accepted
    assert s.train_images.shape == (1, 3, 16, 16) and s.test_images.shape == (1, 3, 16, 16)
    with pytest.raises(InputValueError, match="resolution.*got 15"):
        load_builtin_scene("ar", 15, views=2, test_every=2, samples=1)
    with pytest.raises(InputValueError, match="views=4, test_every=1"):
        load_builtin_scene("ar", 16, views=4, test_every=1, samples=1)
    with pytest.raises(InputValueError, match="views=2, test_every=3"):
        load_builtin_scene("ar", 16, views=2, test_every=3, samples=1)
    with pytest.raises(InputValueError, match="variant.*'xr'"):
        load_builtin_scene("xr", 16, views=2, test_every=2, samples=1)
    with pytest.raises(InputValueError, match="resolution.*8"):
        load_builtin_scene("ar", 8)


# ----------------------------------------------------------------------------- the ground-truth cache

def test_ground_truth_cache_round_trip(tmp_path):
    a = load_builtin_scene("ar", 16, views=4, test_every=2, samples=1, cache=tmp_path)
    files = list(tmp_path.iterdir())
    assert len(files) == 1
    b = load_builtin_scene("ar", 16, views=4, test_every=2, samples=1, cache=tmp_path)
    assert torch.equal(a.train_images, b.train_images) and torch.equal(a.test_images, b.test_images)
    files[0].write_bytes(b"garbage")  # a corrupt cache is rendered again, not trusted
    c = load_builtin_scene("ar", 16, views=4, test_every=2, samples=1, cache=tmp_path)
    assert torch.equal(a.train_images, c.train_images)


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
