"""Tests of ``controlgs_adapter.datasets.base``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers.datasets_synth import marker_image, write_png
from PIL import Image

from controlgs_adapter.datasets import area_resize, check_scene
from controlgs_adapter.datasets.base import Frame, PosedImages, SceneData, working_size
from controlgs_adapter.datasets.memory import tensor_frames
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera


def _cam(w: int, h: int, fx: float = 10.0, fy: float = 12.0, cx: float | None = None, cy: float | None = None) -> Camera:
    k = torch.tensor([[fx, 0.0, w / 2.0 if cx is None else cx], [0.0, fy, h / 2.0 if cy is None else cy], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), k, w, h)


def _rgba_frames(n: int, w: int = 4, h: int = 2) -> list[Frame]:
    imgs = torch.rand(n, 4, h, w, generator=torch.Generator().manual_seed(0))
    return tensor_frames(imgs, [_cam(w, h) for _ in range(n)], prefix="mem")


def _looking(n: int, flipped: int = 0) -> list[Frame]:
    """``n`` cameras at the origin looking down +z (8 x 6, f = 4, centre (4, 3)); the last ``flipped`` look down -z."""
    out = []
    for i in range(n):
        cam = _cam(8, 6, fx=4.0, fy=4.0)
        if i >= n - flipped:
            cam.world_to_camera[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
        out.append(Frame(f"v{i}", cam, torch.zeros(3, 6, 8)))
    return out


@pytest.mark.parametrize("w, h, kw, want", [
    (1000, 600, {}, (1000, 600)),
    (1000, 600, {"resolution": 500}, (500, 300)),
    (600, 1000, {"resolution": 500}, (300, 500)),
    (1000, 600, {"resolution": 2000}, (1000, 600)),  # never upscaled
    (1000, 600, {"factor": 3}, (333, 200)),
    (1000, 600, {"factor": 2.5}, (400, 240)),
    (1000, 600, {"factor": 1}, (1000, 600)),
    (3, 1, {"factor": 4.0}, (1, 1)),  # at least one pixel
    (5, 3, {"resolution": 2}, (2, 1)),
])
def test_working_size_by_hand(w, h, kw, want):
    assert working_size(w, h, **kw) == want


@pytest.mark.parametrize("kw, words", [
    ({"resolution": 4, "factor": 2.0}, "give resolution or factor, not both (got 4 and 2.0)"),
    ({"resolution": 1}, "resolution must be an int >= 2 (longer side in pixels), got 1"),
    ({"resolution": True}, "resolution must be an int >= 2"),
    ({"resolution": 4.0}, "resolution must be an int >= 2"),
    ({"factor": 0.5}, "factor must be a finite number >= 1, got 0.5"),
    ({"factor": float("inf")}, "factor must be a finite number >= 1, got inf"),
    ({"factor": True}, "factor must be a finite number >= 1, got True"),
    ({"factor": "2"}, "factor must be a finite number >= 1, got '2'"),
])
def test_working_size_refusals(kw, words):
    with pytest.raises(InputValueError) as e:
        working_size(10, 10, **kw)
    assert words in str(e.value)


def test_cache_keeps_the_most_recent_views_within_its_byte_budget():
    frames = _rgba_frames(3)  # each decoded view: 3 x 2 x 4 float32 = 96 bytes
    views = PosedImages(frames, cache_bytes=200)  # room for two
    a0, a1 = views.image(0), views.image(1)
    assert views.image(0) is a0 and views.image(1) is a1  # hits
    views.image(0)  # 0 is now the most recent: loading 2 evicts 1
    a2 = views.image(2)
    assert views.image(0) is a0 and views.image(2) is a2
    b1 = views.image(1)
    assert b1 is not a1 and torch.equal(b1, a1)  # reloaded, same pixels
    assert views._cached_bytes == 192 and sorted(views._cache) == [1, 2]  # 0 was least recent when 1 came back
    assert views.image(-1) is a2  # negative index is the last view
    with pytest.raises(IndexError):
        views.image(3)


def test_cache_exactly_full_budget_and_zero_budget():
    views = PosedImages(_rgba_frames(2), cache_bytes=192)  # exactly two
    a0, a1 = views.image(0), views.image(1)
    assert views.image(0) is a0 and views.image(1) is a1 and views._cached_bytes == 192
    none = PosedImages(_rgba_frames(2), cache_bytes=0)
    assert none.image(0) is not none.image(0) and none._cached_bytes == 0
    small = PosedImages(_rgba_frames(2), cache_bytes=95)  # one view does not fit: nothing cached, nothing evicted
    assert small.image(0) is not small.image(0) and len(small._cache) == 0


@pytest.mark.parametrize("bad", [-1, 1.5, True, None])
def test_cache_bytes_refused(bad):
    with pytest.raises(InputValueError, match=f"cache_bytes must be an int >= 0, got {bad!r}"):
        PosedImages(_rgba_frames(1), cache_bytes=bad)


def test_posed_images_rescale_cameras_per_frame_and_describe():
    frames = [Frame("a", _cam(8, 4, fx=10, fy=12, cx=4.5, cy=2.25), torch.rand(3, 4, 8)),
              Frame("b", _cam(4, 4, fx=6, fy=6), torch.rand(3, 4, 4))]
    views = PosedImages(frames, factor=2.0, name="n")
    k = views.camera(0).intrinsics
    assert views.camera(0).width == 4 and views.camera(0).height == 2
    assert k[0].tolist() == [5.0, 0.0, 2.25] and k[1].tolist() == [0.0, 6.0, 1.125] and k[2].tolist() == [0, 0, 1]
    assert views.sizes == [(2, 4), (2, 2)]
    assert views.describe() == {"views": 2, "sizes": ["2x2", "4x2"]}
    full = PosedImages(frames)
    assert full.camera(0) is frames[0].camera  # full size: the frame's own camera
    assert torch.allclose(views.image(0), torch.nn.functional.avg_pool2d(frames[0].source[None], 2)[0])
    with pytest.raises(InputValueError, match="^n: no frames$"):
        PosedImages([], name="n")


def test_fingerprint_tracks_names_sizes_and_poses_only():
    frames = _rgba_frames(2)
    fp = PosedImages(frames).fingerprint()
    assert len(fp) == 16 and PosedImages(_rgba_frames(2)).fingerprint() == fp
    assert PosedImages(tensor_frames(torch.zeros(2, 3, 2, 4), [f.camera for f in frames], prefix="mem")).fingerprint() == fp
    assert PosedImages(tensor_frames(torch.zeros(2, 3, 2, 4), [f.camera for f in frames], prefix="other")).fingerprint() != fp
    assert PosedImages(frames, factor=2.0).fingerprint() != fp
    moved = _cam(4, 2)
    moved.world_to_camera[0, 3] = 1.0
    assert PosedImages([frames[0], Frame(frames[1].name, moved, frames[1].source)]).fingerprint() != fp
    assert PosedImages(frames[::-1]).fingerprint() != fp


def test_scene_views_split_first_and_refusals():
    frames = _rgba_frames(3)
    scene = SceneData({"train": frames, "test": []}, source="src")
    assert len(scene.views("train")) == 3 and len(scene.views("train", first=2)) == 2
    assert [f.name for f in scene.views("train", first=0).frames] == ["mem/0000"]  # at least one
    assert scene.views("train").name == "src:train"
    assert scene.views("train", cache_bytes=0).cache_bytes == 0
    assert scene.views("train", resolution=2).sizes == [(1, 2)] * 3
    with pytest.raises(InputValueError, match=r"^src: no split 'val' \(splits: \['test', 'train'\]\)$"):
        scene.views("val")
    with pytest.raises(InputValueError, match="^src: the 'test' split is empty$"):
        scene.views("test")
    with pytest.raises(InputValueError, match="^dataset: no split"):
        SceneData({"train": frames}).views("x")


def test_check_scene_half_blind_warns_more_than_half_raises_with_the_formats_hint():
    from controlgs_adapter.datasets.sanity import check_scene

    pts = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.0, 2.0]])
    with pytest.warns(RuntimeWarning, match=r"3 of 6 cameras .*: v3, v4, v5$"):
        check_scene(SceneData({"train": _looking(6, flipped=3)}), pts)
    with pytest.warns(RuntimeWarning, match=r"6 of 12 cameras .*: v6, v7, v8, v9, v10, \.\.\.$"):
        check_scene(SceneData({"train": _looking(12, flipped=6)}), pts)
    for fmt, hint in [("blender", "NeRF-synthetic transform_matrix must be camera to world in OpenGL axes"),
                      ("instant_ngp", "instant-ngp transform_matrix must be camera to world"),
                      ("colmap", "COLMAP's images file must hold world to camera"),
                      ("", "this dataset: cameras must be world to camera in OpenCV axes")]:
        with pytest.raises(InputValueError) as e:
            check_scene(SceneData({"train": _looking(3, flipped=2)}, source="s", format=fmt), pts)
        msg = str(e.value)
        assert msg.startswith("s: 2 of 3 cameras see none of the scene") and hint in msg
        assert "fewer than 5% of 2 points" in msg and "on average 67% lie behind the cameras" in msg


def test_area_resize_by_hand():
    """Equal integer factors are an exact box mean (by hand); unequal integer factors (40x60 -> 20x20) are
    not a box of either side: the output has the asked size and keeps a constant image constant."""
    from controlgs_adapter.datasets.base import area_resize

    img = torch.arange(2 * 4 * 6, dtype=torch.float32).reshape(2, 4, 6)
    box = area_resize(img, 2, 3)
    want = torch.tensor([[(0 + 1 + 6 + 7) / 4, (2 + 3 + 8 + 9) / 4, (4 + 5 + 10 + 11) / 4],
                         [(12 + 13 + 18 + 19) / 4, (14 + 15 + 20 + 21) / 4, (16 + 17 + 22 + 23) / 4]])
    assert torch.allclose(box[0], want) and torch.allclose(box[1], want + 24)
    flat = area_resize(torch.full((3, 40, 60), 0.25), 20, 20)
    assert flat.shape == (3, 20, 20) and torch.allclose(flat, torch.full_like(flat, 0.25))


W, H = 32, 24


def test_image_size_mismatch_names_the_file(tmp_path):
    write_png(tmp_path / "a.png", marker_image(W, H, [], rgba=False))
    write_png(tmp_path / "b.png", marker_image(W, H + 2, [], rgba=False))
    k = torch.tensor([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
    cam = Camera(torch.eye(4), k, W, H)
    data = SceneData(splits={"train": [Frame("a.png", cam, tmp_path / "a.png"), Frame("b.png", cam, tmp_path / "b.png")],
                             "test": [Frame("c", cam, torch.zeros(3, H, W + 1))]}, source="synthetic")
    with pytest.raises(FileFormatError, match=rf"2 of 3 images.*b\.png is {W}x{H + 2}, its camera {W}x{H}.*c is {W + 1}x{H}"):
        check_scene(data)


def test_views_first_keeps_the_leading_frames_in_order():
    k = torch.tensor([[20.0, 0, 8.0], [0, 20.0, 6.0], [0, 0, 1]])
    frames = [Frame(f"f{i}", Camera(torch.eye(4), k, 16, 12), torch.full((3, 12, 16), i / 10)) for i in range(5)]
    data = SceneData({"test": frames})
    assert [f.name for f in data.views("test", first=3).frames] == ["f0", "f1", "f2"]
    assert [f.name for f in data.views("test", first=0).frames] == ["f0"]  # at least one
    assert len(data.views("test")) == 5 and len(data.views("test", first=9)) == 5
    cam, img = data.views("test", first=2, resolution=8)[1]
    assert (cam.width, cam.height) == (8, 6) and torch.allclose(img, torch.full((3, 6, 8), 0.1))


@pytest.mark.parametrize("first", ["2", 1.5, True, float("nan")])
def test_views_first_must_be_an_integer(first):
    k = torch.tensor([[20.0, 0, 8.0], [0, 20.0, 6.0], [0, 0, 1]])
    data = SceneData({"test": [Frame("f0", Camera(torch.eye(4), k, 16, 12), torch.zeros(3, 12, 16))]})
    with pytest.raises(InputValueError, match="first"):
        data.views("test", first=first)


def test_sanity_check_counts_points_in_a_wide_image_by_its_width():
    """An 80 x 40 camera; every point projects to u in [44, 76], v in [4, 36]: inside the image (u < W),
    though u > H. The scene is seen, nothing is blind."""
    from controlgs_adapter import Camera
    from controlgs_adapter.datasets.base import Frame, SceneData
    from controlgs_adapter.datasets.sanity import check_scene

    cam = Camera(torch.eye(4), torch.tensor([[40.0, 0.0, 40.0], [0.0, 40.0, 20.0], [0.0, 0.0, 1.0]]), 80, 40)
    g = torch.Generator().manual_seed(0)
    uv = torch.rand(50, 2, generator=g) * torch.tensor([32.0, 32.0]) + torch.tensor([44.0, 4.0])
    pts = torch.cat([(uv - torch.tensor([40.0, 20.0])) / 40.0 * 3.0, torch.full((50, 1), 3.0)], dim=1)  # depth 3
    data = SceneData({"train": [Frame("a", cam, torch.zeros(3, 40, 80))]}, points=pts, source="synthetic", format="builtin")
    report = check_scene(data)
    assert report["in_front"] == {"a": 1.0} and report["blind"] == []


def _two_cameras() -> SceneData:
    """Two 8 x 6 cameras at the origin (f = 4, centre (4, 3)): v0 looks down +z, v1 down -z."""
    frames = []
    for i, flip in enumerate((1.0, -1.0)):
        w2c = torch.eye(4)
        w2c[:3, :3] = torch.diag(torch.tensor([1.0, flip, flip]))
        k = torch.tensor([[4.0, 0, 4], [0, 4.0, 3], [0, 0, 1]])
        frames.append(Frame(f"v{i}", Camera(w2c, k, 8, 6), torch.zeros(3, 6, 8)))
    return SceneData({"train": frames}, source="src")


def test_working_size_defaults_keep_the_size():
    assert working_size(640, 480) == (640, 480)
    assert working_size(640, 480, resolution=320) == (320, 240)
    assert working_size(640, 480, factor=4) == (160, 120)


def test_posed_images_defaults_1_gib_cache_views_name_black_background():
    from controlgs_adapter.datasets.base import PosedImages

    with pytest.raises(InputValueError, match=r"^views: no frames$"):
        PosedImages([])
    data = _two_cameras()
    p = PosedImages(data.splits["train"])
    assert p.cache_bytes == 1 << 30 == 1073741824 and p.name == "views" and p.background.tolist() == [0.0, 0.0, 0.0]
    v = data.views("train")  # SceneData.views: the same cache budget, named source:split, full size
    assert (v.cache_bytes, v.name, v.camera(0).width) == (1 << 30, "src:train", 8)
    assert data.views("train", cache_bytes=0).cache_bytes == 0
    assert len(data.views("train", first=1)) == 1 and len(v) == 2


W_2, H_2, F = 8, 6, 10.0


#: OpenCV camera at the origin looking down +z, and one turned round (looking down -z)
FRONT = torch.eye(4)


def _camera(w2c: torch.Tensor = FRONT, w: int = W_2, h: int = H_2, f: float = F) -> Camera:
    k = torch.tensor([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    return Camera(w2c.clone(), k, w, h)


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
    rgba = torch.zeros(4, H_2, W_2, dtype=torch.float64)
    rgba[:3], rgba[3] = 0.8, 0.25
    data = SceneData({"train": [Frame("a", _camera(), rgba)]})
    assert torch.equal(data.background, torch.zeros(3))
    img = data.views("train").image(0)
    torch.testing.assert_close(img, torch.full((3, H_2, W_2), 0.2))
    bg = torch.tensor([1.0, 0.0, 0.5], requires_grad=True)
    img = PosedImages(data.splits["train"], background=bg).image(0)
    assert not img.requires_grad
    torch.testing.assert_close(img, (0.2 + 0.75 * bg.detach())[:, None, None].expand(3, H_2, W_2))


def test_cache_holds_an_image_exactly_the_size_of_its_budget():
    """``cache_bytes`` is the budget "of at most": an image of exactly that many bytes is kept."""
    frames = [Frame("a", _camera(), torch.rand(3, H_2, W_2, dtype=torch.float64))]
    size = 3 * H_2 * W_2 * 4                                     # float32 [3, H, W]
    views = PosedImages(frames, cache_bytes=size)
    assert views.image(0) is views.image(0)
    views = PosedImages(frames, cache_bytes=size - 1)
    first, second = views.image(0), views.image(0)
    assert first is not second and torch.equal(first, second)


def test_fingerprint_is_pinned_to_its_recipe():
    """A checkpoint records the fingerprint of its training views: the value must not drift between
    releases. Recipe: sha256 over each frame's name, "WxH", world-to-camera (float64, rounded to 6
    decimals) and intrinsics (float64, rounded to 4), first 16 hex digits."""
    import hashlib

    from controlgs_adapter.datasets.base import PosedImages
    from controlgs_adapter.datasets.memory import tensor_frames
    from controlgs_adapter.state import Camera

    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, 3] = torch.tensor([0.1234567, -2.0, 3.5], dtype=torch.float64)
    k = torch.tensor([[10.12345, 0.0, 4.0], [0.0, 11.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cams = [Camera(w2c.float(), k.float(), 8, 6), Camera(w2c.float(), (k * torch.tensor([[0.5], [0.5], [1.0]])).float(), 4, 3)]
    views = PosedImages(tensor_frames([torch.zeros(3, 6, 8), torch.zeros(3, 3, 4)], cams, prefix="fp"))
    h = hashlib.sha256()
    for name, cam in zip(("fp/0000", "fp/0001"), cams):
        h.update(name.encode())
        h.update(f"{cam.width}x{cam.height}".encode())
        h.update(cam.world_to_camera.double().numpy().round(6).tobytes())
        h.update(cam.intrinsics.double().numpy().round(4).tobytes())
    assert views.fingerprint() == h.hexdigest()[:16]
    # a pose change below the rounding (1e-7) keeps it, one above (1e-5) changes it
    near = Camera(cams[0].world_to_camera + 1e-8, cams[0].intrinsics, 8, 6)
    assert PosedImages(tensor_frames([torch.zeros(3, 6, 8), torch.zeros(3, 3, 4)], [near, cams[1]],
                                     prefix="fp")).fingerprint() == views.fingerprint()


def _frames(sizes: list[tuple[int, int]]) -> list[Frame]:
    k = torch.tensor([[4.0, 0.0, 4.0], [0.0, 4.0, 3.0], [0.0, 0.0, 1.0]])
    return [Frame(f"v{i}", Camera(torch.eye(4), k, 8, 6), torch.zeros(3, h, w)) for i, (w, h) in enumerate(sizes)]


@pytest.mark.parametrize("n_bad, tail", [(5, "v4 is 9x6, its camera 8x6"), (6, "v4 is 9x6, its camera 8x6; ...")])
def test_size_check_names_five_images_then_ellipsis(n_bad, tail):
    """At most five mismatched images are named; '; ...' follows only when there are more."""
    data = SceneData({"train": _frames([(9, 6)] * n_bad + [(8, 6)])}, source="src")
    with pytest.raises(FileFormatError) as e:
        check_scene(data)
    msg = str(e.value)
    assert msg.startswith(f"{n_bad} of {n_bad + 1} images do not match their camera's size: v0 is 9x6")
    assert msg.endswith(tail) and msg.count(" is 9x6") == 5
