"""Tests of ``controlgs_adapter.datasets.base``: the working size, area downscaling, and ``PosedImages`` /
``SceneData.views`` (rescaled cameras, the decoded-image cache, fingerprints, splits, backgrounds)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch
from helpers.dataset_views import looking, pinhole
from PIL import Image

from controlgs_adapter.datasets import area_resize
from controlgs_adapter.datasets.base import Frame, PosedImages, SceneData, working_size
from controlgs_adapter.datasets.memory import tensor_frames
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.state import Camera


def _rgba_frames(n: int, w: int = 4, h: int = 2) -> list[Frame]:
    """``n`` random RGBA frames of ``w x h`` (each decodes to ``3 h w`` float32: 96 bytes at 4 x 2)."""
    imgs = torch.rand(n, 4, h, w, generator=torch.Generator().manual_seed(0))
    return tensor_frames(imgs, [pinhole(w, h, 10.0, 12.0) for _ in range(n)], prefix="mem")


# ----------------------------------------------------------------------------- working_size

@pytest.mark.parametrize("w, h, kw, want", [
    (640, 480, {}, (640, 480)),
    (1000, 600, {"resolution": 500}, (500, 300)),
    (600, 1000, {"resolution": 500}, (300, 500)),
    (640, 480, {"resolution": 320}, (320, 240)),
    (1000, 600, {"resolution": 2000}, (1000, 600)),  # never upscaled
    (1000, 600, {"factor": 3}, (333, 200)),
    (1000, 600, {"factor": 2.5}, (400, 240)),
    (640, 480, {"factor": 4}, (160, 120)),
    (1000, 600, {"factor": 1}, (1000, 600)),
    (5, 3, {"resolution": 2}, (2, 1)),
    # at least one pixel on the short side: 1 / 50 rounds to 0
    (3, 1, {"factor": 4.0}, (1, 1)),
    (1, 100, {"resolution": 2}, (1, 2)),
    (100, 1, {"resolution": 2}, (2, 1)),
    (1, 9, {"factor": 4.0}, (1, 2)),
])
def test_working_size(w, h, kw, want):
    assert working_size(w, h, **kw) == want


@pytest.mark.parametrize("kw, pattern", [
    ({"resolution": 4, "factor": 2.0}, r"resolution or factor.*4.*2\.0"),
    ({"resolution": 1}, r"resolution.*got 1$"),
    ({"resolution": True}, r"resolution.*got True$"),
    ({"resolution": 4.0}, r"resolution.*got 4\.0$"),
    ({"factor": 0.5}, r"factor.*got 0\.5$"),
    ({"factor": float("inf")}, r"factor.*got inf$"),
    ({"factor": True}, r"factor.*got True$"),
    ({"factor": "2"}, r"factor.*got '2'$"),
])
def test_working_size_refusals_name_the_argument_and_value(kw, pattern):
    with pytest.raises(InputValueError, match=pattern):
        working_size(10, 10, **kw)


# ----------------------------------------------------------------------------- area_resize

def test_area_resize():
    """Equal integer factors are an exact box mean; unequal ones (40 x 60 -> 20 x 20) keep the asked size and a
    constant image constant; a non-integer factor is the antialiased bilinear filter Pillow's BILINEAR resize
    applies when reducing (plain bilinear would alias); the same size returns the input itself."""
    img = torch.arange(2 * 4 * 6, dtype=torch.float32).reshape(2, 4, 6)
    box = area_resize(img, 2, 3)
    want = torch.tensor([[(0 + 1 + 6 + 7) / 4, (2 + 3 + 8 + 9) / 4, (4 + 5 + 10 + 11) / 4],
                         [(12 + 13 + 18 + 19) / 4, (14 + 15 + 20 + 21) / 4, (16 + 17 + 22 + 23) / 4]])
    assert torch.allclose(box[0], want) and torch.allclose(box[1], want + 24)
    flat = area_resize(torch.full((3, 40, 60), 0.25), 20, 20)
    assert flat.shape == (3, 20, 20) and torch.allclose(flat, torch.full_like(flat, 0.25))
    odd = np.random.default_rng(0).uniform(size=(2, 11, 17)).astype(np.float32)
    out = area_resize(torch.from_numpy(odd), 4, 6)
    ref = np.stack([np.asarray(Image.fromarray(c, "F").resize((6, 4), Image.BILINEAR)) for c in odd])
    assert out.shape == (2, 4, 6)
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-5)
    x = torch.rand(3, 5, 7)
    assert area_resize(x, 5, 7) is x


# ----------------------------------------------------------------------------- PosedImages

def test_posed_images_defaults():
    """A 1 GiB cache, the name "views", a black background; no frames is refused naming the views."""
    with pytest.raises(InputValueError, match=r"^views: no frames$"):
        PosedImages([])
    with pytest.raises(InputValueError, match="^n: no frames$"):
        PosedImages([], name="n")
    p = PosedImages(looking(2, flipped=1))
    assert p.cache_bytes == 1 << 30 and p.name == "views" and p.background.tolist() == [0.0, 0.0, 0.0]


def test_posed_images_rescale_cameras_per_frame_and_describe():
    frames = [Frame("a", pinhole(8, 4, 10, 12, cx=4.5, cy=2.25), torch.rand(3, 4, 8)),
              Frame("b", pinhole(4, 4, 6), torch.rand(3, 4, 4))]
    views = PosedImages(frames, factor=2.0, name="n")
    k = views.camera(0).intrinsics
    assert views.camera(0).width == 4 and views.camera(0).height == 2
    assert k[0].tolist() == [5.0, 0.0, 2.25] and k[1].tolist() == [0.0, 6.0, 1.125] and k[2].tolist() == [0, 0, 1]
    assert views.sizes == [(2, 4), (2, 2)]
    assert views.describe() == {"views": 2, "sizes": ["2x2", "4x2"]}
    assert PosedImages(frames).camera(0) is frames[0].camera  # full size: the frame's own camera
    assert torch.allclose(views.image(0), torch.nn.functional.avg_pool2d(frames[0].source[None], 2)[0])


def test_cache_keeps_the_most_recent_views_within_its_byte_budget():
    views = PosedImages(_rgba_frames(3), cache_bytes=200)  # each decoded view is 96 bytes: room for two
    a0, a1 = views.image(0), views.image(1)
    assert views.image(0) is a0 and views.image(1) is a1  # hits
    views.image(0)  # 0 is now the most recent: loading 2 evicts 1
    a2 = views.image(2)
    assert views.image(0) is a0 and views.image(2) is a2
    b1 = views.image(1)
    assert b1 is not a1 and torch.equal(b1, a1)  # reloaded, same pixels
    assert views._cached_bytes == 192 and sorted(views._cache) == [1, 2]  # 0 was least recent when 1 came back
    assert views.image(-1) is a2  # a negative index is the last view
    with pytest.raises(IndexError):
        views.image(3)


def test_cache_budget_is_inclusive_and_zero_caches_nothing():
    """A budget of exactly the decoded size keeps the image(s); one byte less, or 0, keeps nothing (and
    evicts nothing); a reload gives the same pixels."""
    views = PosedImages(_rgba_frames(2), cache_bytes=192)  # exactly two
    a0, a1 = views.image(0), views.image(1)
    assert views.image(0) is a0 and views.image(1) is a1 and views._cached_bytes == 192
    single = [Frame("a", pinhole(8, 6), torch.rand(3, 6, 8, dtype=torch.float64))]
    size = 3 * 6 * 8 * 4  # float32 [3, H, W]
    exact = PosedImages(single, cache_bytes=size)
    assert exact.image(0) is exact.image(0)
    short = PosedImages(single, cache_bytes=size - 1)
    first, second = short.image(0), short.image(0)
    assert first is not second and torch.equal(first, second) and len(short._cache) == 0
    none = PosedImages(_rgba_frames(2), cache_bytes=0)
    assert none.image(0) is not none.image(0) and none._cached_bytes == 0


@pytest.mark.parametrize("bad", [-1, 1.5, True, None])
def test_cache_bytes_refused(bad):
    with pytest.raises(InputValueError, match=rf"cache_bytes.*got {bad!r}$"):
        PosedImages(_rgba_frames(1), cache_bytes=bad)


def test_fingerprint_tracks_names_sizes_and_poses_only():
    frames = _rgba_frames(2)
    fp = PosedImages(frames).fingerprint()
    assert len(fp) == 16 and PosedImages(_rgba_frames(2)).fingerprint() == fp
    assert PosedImages(tensor_frames(torch.zeros(2, 3, 2, 4), [f.camera for f in frames], prefix="mem")).fingerprint() == fp
    assert PosedImages(tensor_frames(torch.zeros(2, 3, 2, 4), [f.camera for f in frames], prefix="other")).fingerprint() != fp
    assert PosedImages(frames, factor=2.0).fingerprint() != fp
    moved = pinhole(4, 2, 10, 12)
    moved.world_to_camera[0, 3] = 1.0
    assert PosedImages([frames[0], Frame(frames[1].name, moved, frames[1].source)]).fingerprint() != fp
    assert PosedImages(frames[::-1]).fingerprint() != fp


def test_fingerprint_is_pinned_to_its_recipe():
    """A checkpoint records the fingerprint of its training views: the value must not drift between releases.
    Recipe: sha256 over each frame's name, "WxH", world-to-camera (float64, rounded to 6 decimals) and
    intrinsics (float64, rounded to 4), first 16 hex digits."""
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, 3] = torch.tensor([0.1234567, -2.0, 3.5], dtype=torch.float64)
    k = torch.tensor([[10.12345, 0.0, 4.0], [0.0, 11.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cams = [Camera(w2c.float(), k.float(), 8, 6), Camera(w2c.float(), (k * torch.tensor([[0.5], [0.5], [1.0]])).float(), 4, 3)]
    images = [torch.zeros(3, 6, 8), torch.zeros(3, 3, 4)]
    views = PosedImages(tensor_frames(images, cams, prefix="fp"))
    h = hashlib.sha256()
    for name, cam in zip(("fp/0000", "fp/0001"), cams):
        h.update(name.encode())
        h.update(f"{cam.width}x{cam.height}".encode())
        h.update(cam.world_to_camera.double().numpy().round(6).tobytes())
        h.update(cam.intrinsics.double().numpy().round(4).tobytes())
    assert views.fingerprint() == h.hexdigest()[:16]
    # a pose change below the rounding keeps it
    near = Camera(cams[0].world_to_camera + 1e-8, cams[0].intrinsics, 8, 6)
    assert PosedImages(tensor_frames(images, [near, cams[1]], prefix="fp")).fingerprint() == views.fingerprint()


# ----------------------------------------------------------------------------- SceneData

def test_scene_views_by_split_first_size_and_cache():
    """``views(split, first=n)`` keeps the first n frames in order (at least one, at most all), named
    ``source:split``, at the asked size with the default cache budget; unknown and empty splits are refused
    naming the source."""
    frames = [Frame(f"f{i}", pinhole(16, 12, 20.0), torch.full((3, 12, 16), i / 10)) for i in range(5)]
    data = SceneData({"train": frames, "test": []}, source="src")
    v = data.views("train")
    assert (len(v), v.name, v.cache_bytes, v.camera(0).width) == (5, "src:train", 1 << 30, 16)
    assert [f.name for f in data.views("train", first=3).frames] == ["f0", "f1", "f2"]
    assert [f.name for f in data.views("train", first=0).frames] == ["f0"]  # at least one
    assert len(data.views("train", first=9)) == 5
    assert data.views("train", cache_bytes=0).cache_bytes == 0
    cam, img = data.views("train", first=2, resolution=8)[1]
    assert (cam.width, cam.height) == (8, 6) and torch.allclose(img, torch.full((3, 6, 8), 0.1))
    with pytest.raises(InputValueError, match=r"^src: no split 'val' \(splits: \['test', 'train'\]\)$"):
        data.views("val")
    with pytest.raises(InputValueError, match="^src: the 'test' split is empty$"):
        data.views("test")
    with pytest.raises(InputValueError, match="^dataset: no split"):
        SceneData({"train": frames}).views("x")


@pytest.mark.parametrize("first", ["2", 1.5, True, float("nan")])
def test_views_first_must_be_an_integer(first):
    data = SceneData({"test": [Frame("f0", pinhole(16, 12, 20.0), torch.zeros(3, 12, 16))]})
    with pytest.raises(InputValueError, match="first"):
        data.views("test", first=first)


def test_scene_data_default_background_is_black_and_loaded_images_carry_no_graph():
    """An RGBA pixel of alpha 0.25 over the default black background keeps a quarter of its colour. A
    background that requires grad is a constant of the loaded images (no graph reaches them)."""
    rgba = torch.zeros(4, 6, 8, dtype=torch.float64)
    rgba[:3], rgba[3] = 0.8, 0.25
    data = SceneData({"train": [Frame("a", pinhole(8, 6), rgba)]})
    assert torch.equal(data.background, torch.zeros(3))
    torch.testing.assert_close(data.views("train").image(0), torch.full((3, 6, 8), 0.2))
    bg = torch.tensor([1.0, 0.0, 0.5], requires_grad=True)
    img = PosedImages(data.splits["train"], background=bg).image(0)
    assert not img.requires_grad
    torch.testing.assert_close(img, (0.2 + 0.75 * bg.detach())[:, None, None].expand(3, 6, 8))
