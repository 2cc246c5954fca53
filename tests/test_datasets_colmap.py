"""COLMAP dataparser and undistortion, checked against independent implementations: pycolmap writes
the models (binary and text) and projects points; OpenCV undistorts points and images."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from controlgs_adapter.datasets import read_colmap, undistort, undistort_points
from controlgs_adapter.datasets.colmap import (_read_cameras_bin, _read_images_bin, _read_points_bin,
                                               qvec_to_rotation)
from controlgs_adapter.datasets.images import distort_normalized, read_image
from controlgs_adapter.errors import FileFormatError, InputValueError

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
EXPECTED_DIST = {1: None, 2: None, 3: (-0.12, 0.0, 0.0, 0.0, 0.0), 4: (0.08, -0.03, 0.0, 0.0, 0.0),
                 5: (-0.15, 0.04, 0.003, -0.002, 0.0)}


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


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
def test_cameras_poses_points_match_pycolmap(tmp_path, text):
    rec = _reconstruction()
    scene = read_colmap(_write_scene(tmp_path, rec, text=text), holdout=0)
    assert scene.format == "colmap" and scene.splits["test"] == []
    frames = scene.splits["train"]
    assert [f.name for f in frames] == sorted(im.name for im in rec.images.values())
    by_name = {im.name: im for im in rec.images.values()}
    for f in frames:
        im = by_name[f.name]
        cam = rec.camera(im.camera_id)
        k = f.camera.intrinsics.double()
        fx, fy = cam.focal_length_x, cam.focal_length_y
        assert torch.allclose(k, torch.tensor([[fx, 0, cam.principal_point_x], [0, fy, cam.principal_point_y],
                                               [0, 0, 1]], dtype=torch.float64), atol=1e-5)
        assert (f.camera.width, f.camera.height) == (W, H)
        expected_dist = EXPECTED_DIST[im.camera_id]
        assert f.distortion is None if expected_dist is None else f.distortion == pytest.approx(expected_dist)
        w2c = torch.from_numpy(im.cam_from_world().matrix())
        assert torch.allclose(f.camera.world_to_camera[:3].double(), w2c, atol=1e-6)
        assert f.source == tmp_path / "images" / f.name
    xyz = np.stack([p.xyz for p in rec.points3D.values()])
    assert scene.points.dtype == torch.float32
    assert np.allclose(np.sort(scene.points.numpy(), axis=0), np.sort(xyz, axis=0), atol=1e-6)


def test_binary_and_text_read_identically_and_bin_is_preferred(tmp_path):
    rec = _reconstruction(seed=3)
    a = read_colmap(_write_scene(tmp_path / "a", rec), holdout=3)
    b = read_colmap(_write_scene(tmp_path / "b", rec, text=True, sparse="sparse"), holdout=3)
    for split in ("train", "test"):
        for fa, fb in zip(a.splits[split], b.splits[split], strict=True):
            assert fa.name == fb.name and fa.distortion == pytest.approx(fb.distortion)
            assert torch.allclose(fa.camera.world_to_camera, fb.camera.world_to_camera, atol=1e-6)
            assert torch.allclose(fa.camera.intrinsics, fb.camera.intrinsics, atol=1e-5)
    assert torch.allclose(a.points, b.points, atol=1e-6)
    # a text model beside the binary one (different focal lengths) is not read
    other = _reconstruction(seed=3, models={cid: (m, [2 * p[0], *p[1:]]) for cid, (m, p) in MODELS.items()})
    other.write_text(str(tmp_path / "a" / "sparse" / "0"))
    for fa, fb in zip(read_colmap(tmp_path / "a", holdout=3).splits["train"], a.splits["train"]):
        assert torch.equal(fa.camera.intrinsics, fb.camera.intrinsics)


def test_projections_match_pycolmap_and_opencv(tmp_path):
    rec = _reconstruction(n_images=5)
    scene = read_colmap(_write_scene(tmp_path, rec), holdout=0)
    by_name = {im.name: im for im in rec.images.values()}
    pts = np.random.default_rng(2).normal(scale=0.8, size=(50, 3))
    for f in scene.splits["train"]:
        im = by_name[f.name]
        colmap_px = np.stack([im.project_point(p) for p in pts])  # distorted, pixel centres at i + 0.5
        ours, depth = f.camera.project(torch.from_numpy(pts).float())
        assert (depth > 0).all()
        if f.distortion is None:
            np.testing.assert_allclose(ours.numpy(), colmap_px, atol=1e-4)
            continue
        k_cv = _cv_k(f.camera.intrinsics)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
        cv_px = cv2.undistortPoints((colmap_px - 0.5)[:, None], k_cv, np.array(f.distortion), P=k_cv,
                                    criteria=crit)[:, 0] + 0.5
        np.testing.assert_allclose(ours.numpy(), cv_px, atol=1e-4)
        assert np.abs(ours.numpy() - colmap_px).max() > 0.2  # the distortion is not negligible
        inv = undistort_points(torch.from_numpy(colmap_px), f.camera.intrinsics, f.distortion)
        np.testing.assert_allclose(inv.numpy(), ours.double().numpy(), atol=1e-4)


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


def test_split_every_eighth_by_sorted_name(tmp_path):
    rec = _reconstruction(n_images=17, models={1: MODELS[2]})
    root = _write_scene(tmp_path, rec)
    scene = read_colmap(root)
    names = sorted(im.name for im in rec.images.values())
    assert [f.name for f in scene.splits["test"]] == [names[0], names[8], names[16]]
    assert [f.name for f in scene.splits["train"]] == [n for i, n in enumerate(names) if i % 8]
    assert [f.name for f in read_colmap(root, holdout=5).splits["test"]] == names[::5]
    everything = read_colmap(root, holdout=0)
    assert everything.splits["test"] == [] and len(everything.splits["train"]) == 17
    for bad in ({"holdout": -1}, {"holdout": 1.5}, {"resolution": 1}, {"images": "/abs/images"},
                {"background": (1.0, 0.0)}):
        with pytest.raises(InputValueError, match=next(iter(bad))):
            read_colmap(root, **bad)


def test_downscaled_folders_chosen_and_intrinsics_scaled(tmp_path):
    big = (80, 60)
    rec = _reconstruction(n_images=4, models={1: ("PINHOLE", [70.0, 72.0, 40.4, 29.6])}, size=big)
    # Mip-NeRF 360 style: sides rounded (60 / 8 = 7.5 -> 8)
    folders = {"images": big, "images_2": (40, 30), "images_4": (20, 15), "images_8": (10, 8)}
    root = _write_scene(tmp_path, rec, folders=folders)
    for resolution, folder in ((10, "images_8"), (16, "images_4"), (21, "images_2"), (40, "images_2"),
                               (41, "images"), (500, "images")):
        frames = read_colmap(root, resolution=resolution).splits["train"]
        assert all(f.source.parent.name == folder for f in frames), resolution
    assert read_colmap(root).splits["train"][0].source.parent.name == "images"
    for folder, (w, h) in folders.items():
        f = read_colmap(root, images=folder, holdout=0).splits["train"][0]
        assert (f.camera.width, f.camera.height) == (w, h)
        sx, sy = w / big[0], h / big[1]
        expected = torch.tensor([[70.0 * sx, 0, 40.4 * sx], [0, 72.0 * sy, 29.6 * sy], [0, 0, 1]])
        assert torch.allclose(f.camera.intrinsics, expected, atol=1e-5)
    # a folder lacking an image is not chosen by resolution
    (root / "images_8" / rec.image(100).name).unlink()
    assert read_colmap(root, resolution=10).splits["train"][0].source.parent.name == "images_4"
    # an image whose size is not the camera's divided by one factor is refused by name
    bad = root / "images_4" / rec.image(101).name
    Image.new("RGB", (20, 20)).save(bad)
    with pytest.raises(FileFormatError, match=r"images_4/img_.*20x20.*80x60"):
        read_colmap(root, images="images_4")
    with pytest.raises(FileFormatError, match="images_16"):
        read_colmap(root, images="images_16")


@pytest.mark.parametrize("model", ["FULL_OPENCV", "OPENCV_FISHEYE", "FOV"])
def test_unsupported_models_refused(tmp_path, model):
    n = len(pycolmap.Camera.create_from_model_name(1, model, 1.0, W, H).params)
    params = [40.0, 41.0, 20.0, 15.0] + [0.01] * (n - 4)
    rec = _reconstruction(n_images=3, models={1: MODELS[2], 7: (model, params)})
    for text in (False, True):
        root = _write_scene(tmp_path / str(text), rec, text=text)
        with pytest.raises(FileFormatError, match=f"camera 7 .* {model} model.*image_undistorter"):
            read_colmap(root)
    # an exotic camera that no image uses is harmless
    rec2 = _reconstruction(n_images=3, models={1: MODELS[2]})
    cam = pycolmap.Camera.create_from_model_name(9, model, 1.0, W, H)
    rec2.add_camera_with_trivial_rig(cam)
    assert len(read_colmap(_write_scene(tmp_path / "unused", rec2), holdout=0).splits["train"]) == 3


def test_truncated_and_oversized_binary_files_refused(tmp_path):
    rec = _reconstruction(n_images=4)
    root = _write_scene(tmp_path, rec)
    sparse = root / "sparse" / "0"
    readers = {"cameras.bin": _read_cameras_bin, "images.bin": _read_images_bin, "points3D.bin": _read_points_bin}
    for name, reader in readers.items():
        data = (sparse / name).read_bytes()
        reader(sparse / name)  # the whole file reads
        # every truncation in the first records, every 4th byte after (a new file each: rewriting one is slow)
        for n in sorted(set(range(min(len(data), 160))) | set(range(160, len(data), 4))):
            cut = tmp_path / f"cut{n}_{name}"
            cut.write_bytes(data[:n])
            with pytest.raises(FileFormatError, match=f"cut{n}_{name}"):
                reader(cut)
        cut = tmp_path / f"long_{name}"
        cut.write_bytes(data + b"\0")
        with pytest.raises(FileFormatError, match="unexpected bytes"):
            reader(cut)
    # a tiny file declaring 1e11 records is refused at once, through the public reader
    for name in readers:
        scene = tmp_path / f"huge_{name}"
        _write_scene(scene, rec)
        (scene / "sparse" / "0" / name).write_bytes(np.uint64(10**11).tobytes() + b"\1" * 64)
        t0 = time.perf_counter()
        with pytest.raises(FileFormatError, match=rf"{name}: declares 100000000000 "):
            read_colmap(scene)
        assert time.perf_counter() - t0 < 2.0  # no allocation or scan of 1e11 records (loaded CI: generous)
    # a huge declared count of 2D points inside an image record
    data = bytearray((sparse / "images.bin").read_bytes())
    first_name_end = data.index(b"\0", 8 + 64)
    data[first_name_end + 1:first_name_end + 9] = np.uint64(10**11).tobytes()
    (sparse / "images.bin").write_bytes(bytes(data))
    with pytest.raises(FileFormatError, match="images.bin: declares 100000000000 2D points of image"):
        read_colmap(root)


def test_model_and_text_errors_name_the_file(tmp_path):
    rec = _reconstruction(n_images=3)
    root = _write_scene(tmp_path, rec, text=True)
    cams = root / "sparse" / "0" / "cameras.txt"
    good = cams.read_text()
    cams.write_text(good + "9 PINHOLE 40 30 1 2 3\n")  # one parameter short
    with pytest.raises(FileFormatError, match=r"cameras.txt:\d+: expected 4 parameters for a PINHOLE camera"):
        read_colmap(root)
    cams.write_text(good + "9 PINHOLE 40 thirty 1 2 3 4\n")
    with pytest.raises(FileFormatError, match=r"cameras.txt:\d+"):
        read_colmap(root)
    cams.write_text(good)
    (root / "sparse" / "0" / "points3D.txt").unlink()
    assert read_colmap(root).points is None  # cameras need no points
    (root / "sparse" / "0" / "images.txt").unlink()
    with pytest.raises(FileFormatError, match="no images.bin/.txt"):
        read_colmap(root)
    with pytest.raises(FileFormatError, match="no COLMAP model"):
        read_colmap(tmp_path / "images")


def test_missing_images_reported(tmp_path):
    rec = _reconstruction(n_images=10)
    root = _write_scene(tmp_path, rec)
    gone = sorted(im.name for im in rec.images.values())[2:5]
    for name in gone:
        (root / "images" / name).unlink()
    with pytest.raises(FileFormatError, match=rf"3 of the 10 images .* missing \(first: {', '.join(gone)}\)"):
        read_colmap(root)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-10, 10, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3))
def test_quaternion_rotation_is_orthonormal_and_matches_pycolmap(q):
    r = qvec_to_rotation(q)  # (w, x, y, z)
    assert torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.det(r).item() == pytest.approx(1.0, abs=1e-12)
    xyzw = np.array([q[1], q[2], q[3], q[0]])
    ref = pycolmap.Rotation3d(xyzw / np.linalg.norm(xyzw)).matrix()
    np.testing.assert_allclose(r.numpy(), ref, atol=1e-10)


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
