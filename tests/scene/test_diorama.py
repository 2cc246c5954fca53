"""Tests of ``controlgs_adapter.scene.diorama``."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.formats.safetensors import save_tensors
from controlgs_adapter.scene import default_cache_dir, diorama_planes, load_builtin_scene, load_texture

pytest.importorskip("skimage")



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


def test_ground_truth_cache_round_trip(tmp_path):
    a = load_builtin_scene("ar", 16, views=4, test_every=2, samples=1, cache=tmp_path)
    files = list(tmp_path.iterdir())
    assert len(files) == 1
    b = load_builtin_scene("ar", 16, views=4, test_every=2, samples=1, cache=tmp_path)
    assert torch.equal(a.train_images, b.train_images) and torch.equal(a.test_images, b.test_images)
    files[0].write_bytes(b"garbage")  # a corrupt cache is rendered again, not trusted
    c = load_builtin_scene("ar", 16, views=4, test_every=2, samples=1, cache=tmp_path)
    assert torch.equal(a.train_images, c.train_images)


def test_builtin_scene_holds_out_every_test_every_th_arc_camera():
    """views=8, test_every=4: test = arc cameras 0 and 4, train = 1, 2, 3, 5, 6, 7 (disjoint, in order)."""
    pytest.importorskip("skimage")
    from controlgs_adapter.scene import load_builtin_scene
    from controlgs_adapter.scene.cameras import arc_cameras

    scene = load_builtin_scene("ar", 16, views=8, test_every=4, samples=1)
    arc = arc_cameras(8, size=16)
    for got, i in zip(scene.test_cameras, (0, 4), strict=True):
        torch.testing.assert_close(got.world_to_camera.double(), arc[i].world_to_camera.double())
    for got, i in zip(scene.train_cameras, (1, 2, 3, 5, 6, 7), strict=True):
        torch.testing.assert_close(got.world_to_camera.double(), arc[i].world_to_camera.double())


F64 = torch.float64


def _t(*v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


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


def _key_name(variant: str, resolution: int, views: int, samples: int, fov: float) -> str:
    """The documented cache key: every argument and the scene version, in this order."""
    return f"builtin-variant{variant}-resolution{resolution}-views{views}-samples{samples}-fov_deg{fov}-scene_version1.safetensors"


def _plant(folder, name: str, n: int, res: int, key: dict) -> torch.Tensor:
    """A cache file holding image i = i / 100 everywhere (not a rendering: a read of it is recognisable)."""
    images = torch.arange(n, dtype=torch.float32).div(100)[:, None, None, None].expand(n, 3, res, res).contiguous()
    save_tensors(folder / name, {"images": images}, {"key": key}, kind="controlgs_builtin_scene_images", format_version=1)
    return images


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
