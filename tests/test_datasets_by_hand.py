"""Dataset pieces by hand: working sizes, the image cache's byte budget (LRU), in-memory frames,
image decoding of files written by Pillow, format detection, and each refusal (type, and the
argument or file named)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from controlgs_adapter.datasets.base import Frame, PosedImages, SceneData, working_size
from controlgs_adapter.datasets.detect import detect_format, load_dataset
from controlgs_adapter.datasets.images import distort_normalized, image_size, load_frame_image, read_image, undistort
from controlgs_adapter.datasets.memory import posed_images, tensor_frames
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera


def _cam(w: int, h: int, fx: float = 10.0, fy: float = 12.0, cx: float | None = None, cy: float | None = None) -> Camera:
    k = torch.tensor([[fx, 0.0, w / 2.0 if cx is None else cx], [0.0, fy, h / 2.0 if cy is None else cy], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), k, w, h)


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


def _rgba_frames(n: int, w: int = 4, h: int = 2) -> list[Frame]:
    imgs = torch.rand(n, 4, h, w, generator=torch.Generator().manual_seed(0))
    return tensor_frames(imgs, [_cam(w, h) for _ in range(n)], prefix="mem")


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


def test_tensor_frames_names_and_counts():
    frames = tensor_frames([torch.zeros(3, 2, 4)] * 2, [_cam(4, 2)] * 2, prefix="p")
    assert [f.name for f in frames] == ["p/0000", "p/0001"]
    with pytest.raises(InputValueError, match="need one camera per image, got 2 images and 1 cameras"):
        tensor_frames(torch.zeros(2, 3, 2, 4), [_cam(4, 2)])
    bg = torch.tensor([0.25, 0.5, 1.0])
    views = posed_images(torch.zeros(1, 4, 2, 4), [_cam(4, 2)], background=bg, name="mine")
    assert views.name == "mine" and views.frames[0].name == "mine/0000"
    assert views.image(0)[:, 0, 0].tolist() == [0.25, 0.5, 1.0]  # alpha 0: all background


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


def test_detect_format_order_and_refusals(tmp_path):
    with pytest.raises(FileFormatError, match="nowhere: dataset folder not found"):
        detect_format(tmp_path / "nowhere")
    root = tmp_path / "d"
    root.mkdir()
    with pytest.raises(FileFormatError, match=r"d: not a dataset folder in a known format \(it holds: nothing\)\. "
                                              r"Each format needs: colmap: sparse/0/"):
        detect_format(root)
    (root / "sub").mkdir()
    for i in range(11):
        (root / f"f{i:02d}.txt").write_text("")
    with pytest.raises(FileFormatError, match=r"it holds: f00.txt, f01.txt, .*f09.txt, \.\.\.\)"):
        detect_format(root)
    (root / "transforms.json").write_text("{}")
    assert detect_format(root) == "instant_ngp"
    (root / "transforms_train.json").write_text("{}")
    assert detect_format(root) == "blender"
    (root / "sparse").mkdir()
    (root / "sparse" / "cameras.txt").write_text("")
    assert detect_format(root) == "colmap"
    (root / "sparse" / "cameras.txt").unlink()
    (root / "sparse" / "0").mkdir()
    (root / "sparse" / "0" / "cameras.bin").write_bytes(b"")
    assert detect_format(root) == "colmap"


def test_load_dataset_format_names_and_images_option(tmp_path):
    (tmp_path / "transforms.json").write_text("{}")
    with pytest.raises(InputValueError, match=r"format must be one of colmap, blender, instant_ngp \(or None to detect "
                                              r"it\), got 'ngp'"):
        load_dataset(tmp_path, format="ngp")
    with pytest.raises(InputValueError, match=r"images='imgs' applies to COLMAP datasets only; .* is read as instant_ngp"):
        load_dataset(tmp_path, format=" Instant-NGP ", images="imgs")
    with pytest.raises(InputValueError, match="images='imgs' applies to COLMAP datasets only; .* is read as blender"):
        load_dataset(tmp_path, format="BLENDER", images="imgs")
    # the forced reader runs: instant-ngp's own refusal of this empty file
    with pytest.raises(FileFormatError, match="'frames' must be a non-empty list"):
        load_dataset(tmp_path, format="instant-ngp")



# --- COLMAP text models written by hand (no pycolmap)


def _colmap_txt(root, cameras: str, images: str, points: str | None = "1 0.5 -1 2 10 20 30 0.1 1 0\n",
                sizes: dict[str, tuple[int, int]] | None = None):
    from PIL import Image

    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    (sparse / "cameras.txt").write_text("# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]\n" + cameras)
    (sparse / "images.txt").write_text("# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n" + images)
    if points is not None:
        (sparse / "points3D.txt").write_text(points)
    (root / "images").mkdir(exist_ok=True)
    for name, (w, h) in (sizes or {}).items():
        Image.fromarray(np.zeros((h, w, 3), np.uint8)).save(root / "images" / name)
    return root


_CAM = "1 PINHOLE 8 6 10 12 4 3\n"
_IMGS = "1 1 0 0 0 1 2 3 1 b.png\n\n2 0 0 0 1 0 0 0 1 a.png\n1.0 2.0 -1\n"


def test_colmap_text_by_hand_pose_intrinsics_split_and_points(tmp_path):
    from controlgs_adapter.datasets.colmap import read_colmap

    root = _colmap_txt(tmp_path, _CAM, _IMGS, sizes={"a.png": (4, 3), "b.png": (4, 3)})
    scene = read_colmap(root, holdout=2, images="images")
    test, train = scene.splits["test"], scene.splits["train"]
    assert [f.name for f in test] == ["a.png"] and [f.name for f in train] == ["b.png"]  # index 0 of sorted names
    a, b = test[0].camera, train[0].camera
    assert (a.width, a.height) == (4, 3)
    assert a.intrinsics.tolist() == [[5.0, 0.0, 2.0], [0.0, 6.0, 1.5], [0.0, 0.0, 1.0]]  # half size
    # q = (0, 0, 0, 1): 180 degrees about z
    assert a.world_to_camera.tolist() == [[-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    assert b.world_to_camera[:3, 3].tolist() == [1.0, 2.0, 3.0] and b.world_to_camera[:3, :3].tolist() == np.eye(3).tolist()
    assert scene.points.tolist() == [[0.5, -1.0, 2.0]] and scene.points.dtype == torch.float32
    assert scene.format == "colmap" and scene.source == str(root)
    assert len(read_colmap(root, holdout=0).splits["test"]) == 0
    assert scene.background.tolist() == [0.0, 0.0, 0.0]
    assert read_colmap(root, background=(0.5, 0.25, 1.0)).background.tolist() == [0.5, 0.25, 1.0]


@pytest.mark.parametrize("kw, words", [
    ({"holdout": -1}, "holdout must be an int >= 0 (every holdout-th view is a test view), got -1"),
    ({"holdout": True}, "holdout must be an int >= 0"),
    ({"holdout": 2.0}, "holdout must be an int >= 0"),
    ({"resolution": 1}, "resolution must be an int >= 2 (longer side in pixels), got 1"),
    ({"resolution": False}, "resolution must be an int >= 2"),
    ({"images": ""}, "images must be the name of a folder under the scene root, got ''"),
    ({"images": "/abs"}, "images must be the name of a folder under the scene root, got '/abs'"),
    ({"background": (0.5, 0.5)}, "background must be 3 finite sRGB values, got (0.5, 0.5)"),
    ({"background": (0.5, 0.5, float("nan"))}, "background must be 3 finite sRGB values"),
])
def test_colmap_argument_refusals(tmp_path, kw, words):
    from controlgs_adapter.datasets.colmap import read_colmap

    root = _colmap_txt(tmp_path, _CAM, _IMGS, sizes={"a.png": (8, 6), "b.png": (8, 6)})
    with pytest.raises(InputValueError) as e:
        read_colmap(root, **kw)
    assert words in str(e.value)


@pytest.mark.parametrize("cams, imgs, points, sizes, words", [
    (_CAM, _IMGS.replace("b.png", "a.png"), None, {}, "image name 'a.png' appears twice in the images file"),
    (_CAM, _IMGS.replace(" 1 b.png", " 7 b.png"), None, {}, "image 'b.png' refers to camera 7, which is not in the file"),
    ("1 PINHOLE 0 6 10 12 4 3\n", _IMGS, None, {"a.png": (8, 6), "b.png": (8, 6)}, "the camera of image 'a.png' is invalid"),
    ("1 PINHOLE 8 6 nan 12 4 3\n", _IMGS, None, {"a.png": (8, 6), "b.png": (8, 6)}, "the camera of image 'a.png' is invalid"),
    ("1 PINHOLE 8 6 10 0 4 3\n", _IMGS, None, {"a.png": (8, 6), "b.png": (8, 6)},
     "the camera of image 'a.png' has focal lengths 10.0, 0.0 (must be > 0)"),
    (_CAM, _IMGS.replace("2 0 0 0 1", "2 0 0 0 0"), None, {"a.png": (8, 6), "b.png": (8, 6)},
     "image 'a.png' has a bad quaternion [0.0, 0.0, 0.0, 0.0]"),
    (_CAM, _IMGS.replace("1 1 0 0 0 1 2 3", "1 1 0 0 0 1 inf 3"), None, {"a.png": (8, 6), "b.png": (8, 6)},
     "image 'b.png' has a non-finite translation [1.0, inf, 3.0]"),
    (_CAM, _IMGS, "1 nan 0 0 1 1 1 0\n", {}, "points3D.txt: non-finite 3D point coordinates"),
    (_CAM, _IMGS, "1 0 0 0 1 1 1\n", {}, "points3D.txt:1: expected POINT3D_ID X Y Z R G B ERROR TRACK..."),
    (_CAM, "1 1 0 0 0 1 2 3 1\n", None, {}, "images.txt:2: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"),
    ("1 PINHOLE 8\n", _IMGS, None, {}, "cameras.txt:2: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS... with a known"),
    ("1 PINHOLE_X 8 6 1 1 1 1\n", _IMGS, None, {}, "with a known COLMAP model"),
    (_CAM, _IMGS, None, {"a.png": (8, 6), "b.png": (8, 3)},
     "b.png: image is 8x3, which is not its camera's 8x6 (in "),
])
def test_colmap_model_refusals_name_the_file(tmp_path, cams, imgs, points, sizes, words):
    from controlgs_adapter.datasets.colmap import read_colmap

    root = _colmap_txt(tmp_path, cams, imgs, points=points, sizes=sizes)
    with pytest.raises(FileFormatError) as e:
        read_colmap(root, holdout=0)
    assert words in str(e.value)


def test_colmap_folders_and_encodings_refused(tmp_path):
    from controlgs_adapter.datasets.colmap import read_colmap

    with pytest.raises(FileFormatError, match="nowhere: scene folder not found"):
        read_colmap(tmp_path / "nowhere")
    root = _colmap_txt(tmp_path / "s", _CAM, _IMGS, sizes={"a.png": (8, 6)})
    with pytest.raises(FileFormatError, match=r"images: 1 of the 2 images in .*0 are missing \(first: b.png\)"):
        read_colmap(root)
    with pytest.raises(FileFormatError, match="images_2: images folder not found"):
        read_colmap(root, images="images_2")
    (root / "sparse" / "0" / "cameras.txt").write_bytes(b"1 PINHOLE 8 6 10 12 4 3 \xff\n")
    with pytest.raises(FileFormatError, match="cameras.txt: not a UTF-8 text file"):
        read_colmap(root)
    # the model may sit in sparse/ directly
    flat = tmp_path / "flat"
    _colmap_txt(flat, _CAM, _IMGS, points=None, sizes={"a.png": (8, 6), "b.png": (8, 6)})
    (flat / "sparse" / "0").rename(flat / "sparse0")
    (flat / "sparse").rmdir()
    (flat / "sparse0").rename(flat / "sparse")
    assert read_colmap(flat, holdout=0).points is None and len(read_colmap(flat, holdout=0).splits["train"]) == 2


@pytest.mark.parametrize("size, ok", [((4, 3), True), ((4, 4), True), ((5, 3), True), ((2, 2), True), ((6, 3), True), ((8, 3), False),
                                      ((4, 5), False), ((16, 12), True), ((9, 6), True), ((10, 6), True), ((12, 6), False),
                                      ((3, 4), True), ((13, 6), False)])  # 3 x 4: lo = hi = 1/2 exactly
def test_colmap_image_size_must_be_the_camera_divided_by_one_factor(tmp_path, size, ok):
    from controlgs_adapter.datasets.colmap import read_colmap

    root = _colmap_txt(tmp_path, _CAM, "1 1 0 0 0 0 0 0 1 a.png\n\n", sizes={"a.png": size})
    if ok:
        cam = read_colmap(root, holdout=0).splits["train"][0].camera
        k = cam.intrinsics.tolist()
        assert k[0] == pytest.approx([10 * size[0] / 8, 0, 4 * size[0] / 8]) and k[1] == pytest.approx([0, 12 * size[1] / 6, 3 * size[1] / 6])
    else:
        with pytest.raises(FileFormatError, match="which is not its camera's 8x6"):
            read_colmap(root, holdout=0)


def test_colmap_binary_unknown_model_id_and_non_utf8_name(tmp_path):
    import struct

    from controlgs_adapter.datasets.colmap import _read_cameras_bin, _read_images_bin

    p = tmp_path / "cameras.bin"
    p.write_bytes(struct.pack("<Q", 1) + struct.pack("<IiQQ", 3, 18, 8, 6) + struct.pack("<3d", 1, 2, 3))
    with pytest.raises(FileFormatError, match=r"cameras.bin: camera 3 has unknown model id 18 \(known: 0..17\)"):
        _read_cameras_bin(p)
    p.write_bytes(struct.pack("<Q", 1) + struct.pack("<IiQQ", 3, 0, 8, 6) + struct.pack("<3d", 1, 2, 3))
    cam = _read_cameras_bin(p)[3]
    assert (cam.model, cam.width, cam.height, cam.params) == ("SIMPLE_PINHOLE", 8, 6, (1.0, 2.0, 3.0))
    q = tmp_path / "images.bin"
    head = struct.pack("<I4d3dI", 5, 1, 0, 0, 0, 1, 2, 3, 3)
    q.write_bytes(struct.pack("<Q", 1) + head + b"\xffname\0" + struct.pack("<Q", 0))
    with pytest.raises(FileFormatError, match="images.bin: the name of image 5 at byte .* is not UTF-8"):
        _read_images_bin(q)
    q.write_bytes(struct.pack("<Q", 1) + head + b"x.png\0" + struct.pack("<Q", 1) + b"\0" * 24)
    im = _read_images_bin(q)[5]
    assert (im.qvec, im.tvec, im.camera_id, im.name) == ((1.0, 0.0, 0.0, 0.0), (1.0, 2.0, 3.0), 3, "x.png")


# --- instant-ngp and Blender JSON written by hand

_EYE = [[1.0, 0.0, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0]]


def _ngp(root, meta: dict, frames: list[dict], sizes: dict[str, tuple[int, int]]):
    import json

    from PIL import Image

    root.mkdir(parents=True, exist_ok=True)
    for name, (w, h) in sizes.items():
        Image.fromarray(np.zeros((h, w, 3), np.uint8)).save(root / name)
    (root / "transforms.json").write_text(json.dumps({**meta, "frames": [{"transform_matrix": _EYE, **f} for f in frames]}))
    return root


def test_ngp_intrinsics_defaults_and_group_overrides_by_hand(tmp_path):
    import math

    from controlgs_adapter.datasets.instant_ngp import read_instant_ngp

    meta = {"fl_y": 6.0, "w": 8, "h": 4, "k1": 0.0, "k2": 0.0}
    frames = [{"file_path": "a.png"},
              {"file_path": "b.png", "camera_angle_x": math.pi / 2, "cx": 1.0, "k3": 0.01},
              {"file_path": "c.png", "camera_angle_y": math.pi / 2, "w": 16, "h": 8}]
    root = _ngp(tmp_path, meta, frames, {"a.png": (8, 4), "b.png": (4, 2), "c.png": (8, 4)})
    scene = read_instant_ngp(root, holdout=0)
    a, b, c = scene.splits["train"]
    assert a.camera.intrinsics.tolist() == [[6.0, 0.0, 4.0], [0.0, 6.0, 2.0], [0.0, 0.0, 1.0]]  # fx from fl_y; centre w/2, h/2
    assert a.distortion is None  # all-zero coefficients: pinhole
    # b: its own focal group (fx = 0.5 w / tan(pi/4) = 4; fy from fx), its own cx (cy from the top level's h/2): half size
    np.testing.assert_allclose(b.camera.intrinsics, [[2.0, 0.0, 0.5], [0.0, 2.0, 1.0], [0.0, 0.0, 1.0]], rtol=1e-6)
    assert b.distortion == (0.0, 0.0, 0.0, 0.0, 0.01)  # the frame's distortion group replaces the top level's
    # c: fy = 0.5 h / tan(pi/4) = 4 at 16 x 8, image at half size
    np.testing.assert_allclose(c.camera.intrinsics, [[2.0, 0.0, 4.0], [0.0, 2.0, 2.0], [0.0, 0.0, 1.0]], rtol=1e-6)
    assert scene.points is None and scene.format == "instant_ngp" and scene.source == str(root)


@pytest.mark.parametrize("meta, frame, words", [
    ({"camera_model": "OPENCV_FISHEYE"}, {}, "camera_model 'OPENCV_FISHEYE' is not supported"),
    ({}, {"camera_model": "EQUIRECTANGULAR"}, "camera_model 'EQUIRECTANGULAR' is not supported"),
    ({"is_fisheye": True}, {}, "is_fisheye set: fisheye cameras are not supported"),
    ({}, {"k4": 0.1}, "k4 set: fisheye cameras are not supported"),
    ({"w": 0}, {}, "w and h must be > 0, got 0.0 x 4.0"),
    ({"h": -4}, {}, "w and h must be > 0"),
    ({"fl_x": None}, {}, "fl_x must be a finite number, got None"),
    ({"fl_x": "5"}, {}, "fl_x must be a finite number, got '5'"),
    ({"fl_x": 0.0}, {}, "no usable focal length"),
    ({"fl_x": -1.0, "fl_y": 2.0}, {}, "no usable focal length"),
    ({"fl_x": None}, {"fl_y": 1.0, "camera_angle_x": 0.0}, "camera_angle_x must be in (0, pi) radians, got 0.0"),
    ({}, {"camera_angle_y": 3.2}, "camera_angle_y must be in (0, pi) radians, got 3.2"),
    ({"fl_x": None}, {"cx": 1.0}, "fl_x must be a finite number"),
    ({"w": 8, "h": 2}, {}, "the file says 8 x 2 but the image"),
    ({"w": 6, "h": 4}, {}, "the file says 6 x 4 but the image"),
    ({}, {"transform_matrix": None}, "no 'transform_matrix'"),
    ({}, {"transform_matrix": [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "not a rotation"),
    ({}, {"transform_matrix": [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]]}, "not a rotation"),  # mirrored
])
def test_ngp_camera_refusals_name_file_and_frame(tmp_path, meta, frame, words):
    from controlgs_adapter.datasets.instant_ngp import read_instant_ngp

    root = _ngp(tmp_path, {"fl_x": 5.0, **meta}, [{"file_path": "a.png", **frame}], {"a.png": (8, 4)})
    with pytest.raises(FileFormatError) as e:
        read_instant_ngp(root, holdout=0)
    assert "transforms.json: frames[0] ('a.png')" in str(e.value) and words in str(e.value)


def test_ngp_file_level_refusals_and_missing_frames(tmp_path):
    from controlgs_adapter.datasets.instant_ngp import read_instant_ngp

    with pytest.raises(FileFormatError, match="nowhere: dataset folder not found"):
        read_instant_ngp(tmp_path / "nowhere")
    root = _ngp(tmp_path / "r", {"fl_x": 5.0}, [{"file_path": f"f{i}.png"} for i in range(8)],
                {"f0.png": (8, 4), "f7.png": (8, 4)})
    for bad in (1, -1, True, 2.0):
        with pytest.raises(InputValueError, match=f"holdout must be 0 \\(no test split\\) or an int >= 2, got {bad!r}"):
            read_instant_ngp(root, holdout=bad)
    with pytest.warns(RuntimeWarning, match=r"transforms.json: 6 of 8 frames list an image that is not there, skipped: "
                                            r"f1.png, f2.png, f3.png, f4.png, f5.png, \.\.\.$"):
        scene = read_instant_ngp(root, holdout=2)
    assert [f.name for f in scene.splits["test"]] == ["f0.png"] and [f.name for f in scene.splits["train"]] == ["f7.png"]
    with pytest.raises(FileFormatError, match=r"other.json: not found \(an instant-ngp dataset needs other.json\)"):
        read_instant_ngp(root, transforms="other.json")
    gone = _ngp(tmp_path / "g", {"fl_x": 5.0}, [{"file_path": "x.png"}, {"file_path": "y.png"}], {})
    with pytest.warns(RuntimeWarning, match="skipped: x.png, y.png$"), \
            pytest.raises(FileFormatError, match=r"none of the 2 images its frames list exists \(first: .*g/x.png\)"):
        read_instant_ngp(gone)
    twice = _ngp(tmp_path / "t", {"fl_x": 5.0}, [{"file_path": "a.png"}, {"file_path": "./a"}], {"a.png": (8, 4)})
    with pytest.raises(FileFormatError, match="an image is listed twice \\('a.png'\\)"):
        read_instant_ngp(twice)
    (twice / "transforms.json").write_text('{"frames": []}')
    with pytest.raises(FileFormatError, match=r"'frames' must be a non-empty list, got \[\]"):
        read_instant_ngp(twice)
    (twice / "transforms.json").write_text('[1]')
    with pytest.raises(FileFormatError, match="transforms.json: expected a JSON object, got list"):
        read_instant_ngp(twice)
    (twice / "transforms.json").write_text('{"frames": [')
    with pytest.raises(FileFormatError, match=r"transforms.json: cannot read it as JSON \("):
        read_instant_ngp(twice)
    (twice / "transforms.json").write_text('{"frames": [{"file_path": 3}]}')
    with pytest.raises(FileFormatError, match=r"transforms.json: frames\[0\] needs a 'file_path' string"):
        read_instant_ngp(twice)


def test_blender_by_hand_and_refusals(tmp_path):
    import json
    import math

    from PIL import Image

    from controlgs_adapter.datasets.blender import read_blender

    with pytest.raises(FileFormatError, match="nowhere: dataset folder not found"):
        read_blender(tmp_path / "nowhere")
    with pytest.raises(FileFormatError, match="no transforms_train.json"):
        read_blender(tmp_path)
    (tmp_path / "train").mkdir()
    Image.fromarray(np.zeros((4, 8, 4), np.uint8), "RGBA").save(tmp_path / "train" / "r_0.png")
    meta = {"camera_angle_x": math.pi / 2, "frames": [{"file_path": "./train/r_0", "transform_matrix": _EYE}]}
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    scene = read_blender(tmp_path, white_background=True)
    (f,) = scene.splits["train"]
    assert scene.splits["test"] == [] and f.name == "train/r_0.png" and scene.background.tolist() == [1.0, 1.0, 1.0]
    np.testing.assert_allclose(f.camera.intrinsics, [[4.0, 0.0, 4.0], [0.0, 4.0, 2.0], [0.0, 0.0, 1.0]], rtol=1e-6)
    # OpenGL camera at (0.5, 0, 2) looking down -z: OpenCV w2c flips y and z, t = -R^T c
    assert f.camera.world_to_camera.tolist() == [[1, 0, 0, -0.5], [0, -1, 0, 0], [0, 0, -1, 2], [0, 0, 0, 1]]
    assert read_blender(tmp_path, background=torch.tensor([0.2, 0.4, 0.6]), white_background=True).background.tolist() \
        == pytest.approx([0.2, 0.4, 0.6])
    with pytest.raises(InputValueError, match=r"background must be an sRGB colour in \[0, 1\], got \[0.0, 2.0, 0.0\]"):
        read_blender(tmp_path, background=torch.tensor([0.0, 2.0, 0.0]))
    for angle in (0.0, math.pi, "1", None):
        (tmp_path / "transforms_train.json").write_text(json.dumps({**meta, "camera_angle_x": angle}))
        with pytest.raises(FileFormatError, match=rf"transforms_train.json: camera_angle_x must be a number in \(0, pi\) "
                                                  rf"radians, got {angle!r}"):
            read_blender(tmp_path)
    (tmp_path / "transforms_train.json").write_text(json.dumps({**meta, "frames": {}}))
    with pytest.raises(FileFormatError, match="transforms_train.json: 'frames' must be a list, got dict"):
        read_blender(tmp_path)
    (tmp_path / "transforms_train.json").write_text(json.dumps({**meta, "frames": [{"file_path": "train/r_1.jpg"}]}))
    with pytest.raises(FileFormatError, match=r"frames\[0\] image 'train/r_1.jpg' not found \(looked for .*r_1.jpg and "
                                              r"with .png appended\)"):
        read_blender(tmp_path)
    (tmp_path / "transforms_train.json").write_text(json.dumps({**meta, "frames": [{"file_path": "train/r_1.png"}]}))
    with pytest.raises(FileFormatError, match=r"r_1.png\)$"):
        read_blender(tmp_path)


# --- check_scene by hand


def _looking(n: int, flipped: int = 0) -> list[Frame]:
    """``n`` cameras at the origin looking down +z (8 x 6, f = 4, centre (4, 3)); the last ``flipped`` look down -z."""
    out = []
    for i in range(n):
        cam = _cam(8, 6, fx=4.0, fy=4.0)
        if i >= n - flipped:
            cam.world_to_camera[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
        out.append(Frame(f"v{i}", cam, torch.zeros(3, 6, 8)))
    return out


def test_check_scene_fractions_and_image_borders_by_hand():
    from controlgs_adapter.datasets.sanity import check_scene

    # u = 4 x / z + 4, v = 4 y / z + 3: inside iff 0 <= u < 8 and 0 <= v < 6
    pts = torch.tensor([[0.0, 0.0, 1.0],      # centre: inside
                        [-1.0, -0.75, 1.0],   # u = 0, v = 0: inside (left/top edges included)
                        [1.0, 0.0, 1.0],      # u = 8: outside (right edge excluded)
                        [0.0, 0.75, 1.0],     # v = 6: outside (bottom edge excluded)
                        [0.0, 0.0, -1.0],     # behind
                        [0.0, 0.0, 0.0],      # depth 0: not in front
                        [0.99, 0.74, 1.0],    # inside
                        [10.0, 0.0, 1.0]])    # outside
    data = SceneData({"train": _looking(2), "test": []}, source="src", format="colmap")
    rep = check_scene(data, pts, required=("train",))
    assert rep["in_front"] == {"v0": 3 / 8, "v1": 3 / 8} and rep["blind"] == [] and rep["points"] == 8
    assert rep["splits"] == {"train": 2, "test": 0} and rep["images_checked"] == 2
    assert (rep["source"], rep["format"]) == ("src", "colmap")
    # a camera exactly at the threshold is not blind
    assert check_scene(data, pts, min_in_front=3 / 8)["blind"] == []
    with pytest.warns(RuntimeWarning, match=r"src: 1 of 2 cameras see almost none of the 8 points \(< 38% in front"):
        assert check_scene(SceneData({"train": _looking(2, flipped=1)}, source="src"), pts, min_in_front=0.375)["blind"] \
            == ["v1"]


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


def test_check_scene_points_choice_stride_and_refusals():
    from controlgs_adapter.datasets import sanity

    data = SceneData({"train": _looking(1)}, points=torch.tensor([[0.0, 0.0, -1.0]]), source="s")
    with pytest.raises(InputValueError, match="1 of 1 cameras"):
        sanity.check_scene(data)  # the SfM points, behind the camera
    assert sanity.check_scene(data, torch.tensor([[0.0, 0.0, 1.0]]))["in_front"] == {"v0": 1.0}  # given points win
    assert sanity.check_scene(data, torch.zeros(0, 3))["points"] == 0
    assert sanity.check_scene(SceneData({"train": _looking(1)}))["in_front"] == {}  # no points: skipped
    n = sanity._MAX_POINTS + 1
    assert sanity.check_scene(data, torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1))["points"] == (n + 1) // 2
    for bad in (-0.1, 1.0, True, "0.5"):
        with pytest.raises(InputValueError, match=f"min_in_front must be a fraction in \\[0, 1\\), got {bad!r}"):
            sanity.check_scene(data, min_in_front=bad)
    with pytest.raises(InputValueError, match=r"^s: the 'test' split is empty \(splits: train=1\)$"):
        sanity.check_scene(data, required=("train", "test"))
    with pytest.raises(InputValueError, match=r"the 'train' split is empty \(splits: none\)$"):
        sanity.check_scene(SceneData({}))
    frames = [Frame(f"w{i}", _cam(8, 6), torch.zeros(3, 6, 7)) for i in range(7)]
    with pytest.raises(FileFormatError, match=r"^7 of 8 images do not match their camera's size: w0 is 7x6, its camera "
                                              r"8x6; .*w4 is 7x6, its camera 8x6; \.\.\.$"):
        sanity.check_scene(SceneData({"train": _looking(1) + frames}))
