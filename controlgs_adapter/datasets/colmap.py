"""COLMAP sparse models (``sparse/0/{cameras,images,points3D}.{bin,txt}``) read into a
:class:`~controlgs_adapter.datasets.base.SceneData`.

This is a small reader of COLMAP's documented model format rather than a ``pycolmap`` dependency:
the format is a few fixed little-endian records, while pycolmap is a large binary wheel whose
Python API changes between releases.

Conventions (COLMAP's "Output format" documentation): an image's quaternion ``(w, x, y, z)`` and
translation map world to camera in OpenCV axes (``x_cam = R(q) x_world + t``); image coordinates put
the centre of the top-left pixel at (0.5, 0.5), as :class:`~controlgs_adapter.state.Camera` does, so
intrinsics are taken as they are. The intrinsics belong to the full-size images and are scaled to
the size of the image files read (Mip-NeRF 360's ``images_2|4|8``). SIMPLE_RADIAL, RADIAL and OPENCV
cameras become pinhole cameras with OpenCV distortion coefficients; their images are undistorted on
load (:func:`~controlgs_adapter.datasets.images.undistort`).

Every binary parser checks each declared count against the bytes left in the file before reading,
so a truncated or foreign file raises :class:`~controlgs_adapter.errors.FileFormatError` naming it.
Text files are read record by record (an image is two lines, the second its POINTS2D line); a missing
POINTS2D line, a repeated id (text or binary) or a header count that differs from the records is
refused naming the line or record. Image names, the images folder and the model files must resolve
inside the scene folder (symlinks followed); nothing outside it is opened.
"""

from __future__ import annotations

import math
import mmap
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from ..errors import FileFormatError, InputValueError
from .base import Frame, SceneData
from .guards import dataset_camera, float32_finite, inside
from .images import image_size

__all__ = ["read_colmap", "qvec_to_rotation", "CAMERA_MODELS"]

#: COLMAP camera models: id -> (name, number of parameters); all are listed so that a cameras file
#: holding an unused exotic camera still parses
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16), 12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5),
    14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4), 16: ("EUCM", 6), 17: ("EQUIRECTANGULAR", 2),
}
_PARAMS_BY_NAME = {name: n for name, n in CAMERA_MODELS.values()}
_SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
#: downscaled image folders (Mip-NeRF 360 / 3DGS), most downscaled first
_DOWNSCALED = (8, 4, 2)

_U64 = struct.Struct("<Q")
_CAMERA_HEAD = struct.Struct("<IiQQ")      # camera_id, model_id, width, height
_IMAGE_HEAD = struct.Struct("<I4d3dI")     # image_id, qw qx qy qz, tx ty tz, camera_id
#: largest finite float32: cameras and points are stored in float32
_F32_MAX = float(np.finfo(np.float32).max)
_POINT2D_BYTES = 24                        # x, y (f64), point3D_id (i64)
_POINT_HEAD_BYTES = 8 + 24 + 3 + 8         # point3D_id, xyz, rgb, error
_TRACK_ELEMENT_BYTES = 8                   # image_id, point2D_idx (u32 each)


@dataclass(frozen=True)
class _ColmapCamera:
    model: str
    width: int
    height: int
    params: tuple[float, ...]
    where: str  # the file and line (text) or record (binary), for messages


@dataclass(frozen=True)
class _ColmapImage:
    qvec: tuple[float, float, float, float]  # w, x, y, z
    tvec: tuple[float, float, float]
    camera_id: int
    name: str
    where: str  # the file and line (text) or record (binary), for messages


# ---------------------------------------------------------------------------------------------
# binary files


class _BinFile:
    """A memory-mapped little-endian file read front to back with bounds checks."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            with open(path, "rb") as fh:
                size = fh.seek(0, 2)
                self.buf: Any = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
        except OSError as e:
            raise FileFormatError(f"{path}: cannot read the file ({e})") from None
        self.size = size
        self.off = 0

    def close(self) -> None:
        if isinstance(self.buf, mmap.mmap):
            self.buf.close()

    def __enter__(self) -> "_BinFile":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def truncated(self, what: str) -> FileFormatError:
        return FileFormatError(f"{self.path}: truncated COLMAP binary file: {what} at byte {self.off} runs past "
                               f"the end ({self.size} bytes)")

    def unpack(self, s: struct.Struct, what: str) -> tuple:
        if self.off + s.size > self.size:
            raise self.truncated(what)
        out = s.unpack_from(self.buf, self.off)
        self.off += s.size
        return out

    def count(self, what: str, min_bytes: int) -> int:
        """Read a u64 count of records of at least ``min_bytes`` each; refuse one the file cannot hold."""
        (n,) = self.unpack(_U64, f"the number of {what}")
        left = self.size - self.off
        if n * min_bytes > left:
            raise FileFormatError(f"{self.path}: declares {n} {what} (at least {min_bytes} bytes each) but only "
                                  f"{left} bytes follow: truncated, or not a COLMAP binary file")
        return n

    def skip(self, nbytes: int, what: str) -> None:
        if self.off + nbytes > self.size:
            raise self.truncated(what)
        self.off += nbytes

    def cstring(self, what: str) -> str:
        end = self.buf.find(b"\0", self.off)
        if end < 0:
            raise self.truncated(what)
        raw = bytes(self.buf[self.off:end])
        self.off = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise FileFormatError(f"{self.path}: {what} at byte {self.off} is not UTF-8") from None

    def finish(self) -> None:
        if self.off != self.size:
            raise FileFormatError(f"{self.path}: {self.size - self.off} unexpected bytes after the last record")


def _read_cameras_bin(path: Path) -> dict[int, _ColmapCamera]:
    cams: dict[int, _ColmapCamera] = {}
    min_params = min(n for _, n in CAMERA_MODELS.values())
    with _BinFile(path) as f:
        n = f.count("cameras", _CAMERA_HEAD.size + 8 * min_params)
        for k in range(n):
            start = f.off
            cam_id, model_id, width, height = f.unpack(_CAMERA_HEAD, "a camera record")
            where = f"{path}: camera record {k} (CAMERA_ID {cam_id}, byte {start})"
            if model_id not in CAMERA_MODELS:
                raise FileFormatError(f"{path}: camera {cam_id} has unknown model id {model_id} (known: "
                                      f"0..{max(CAMERA_MODELS)}), in camera record {k} at byte {start}")
            if cam_id in cams:
                raise FileFormatError(f"{where}: CAMERA_ID {cam_id} appears twice (first: {cams[cam_id].where})")
            name, n_params = CAMERA_MODELS[model_id]
            params = f.unpack(struct.Struct(f"<{n_params}d"), f"the parameters of camera {cam_id}")
            cams[cam_id] = _ColmapCamera(name, width, height, params, where)
        f.finish()
    return cams


def _read_images_bin(path: Path) -> dict[int, _ColmapImage]:
    images: dict[int, _ColmapImage] = {}
    with _BinFile(path) as f:
        n = f.count("images", _IMAGE_HEAD.size + 1 + 8)
        for k in range(n):
            start = f.off
            image_id, qw, qx, qy, qz, tx, ty, tz, cam_id = f.unpack(_IMAGE_HEAD, "an image record")
            where = f"{path}: image record {k} (IMAGE_ID {image_id}, byte {start})"
            if image_id in images:
                raise FileFormatError(f"{where}: IMAGE_ID {image_id} appears twice (first: {images[image_id].where})")
            name = f.cstring(f"the name of image {image_id}")
            n2d = f.count(f"2D points of image {image_id}", _POINT2D_BYTES)
            f.skip(n2d * _POINT2D_BYTES, f"the 2D points of image {image_id}")
            images[image_id] = _ColmapImage((qw, qx, qy, qz), (tx, ty, tz), cam_id, name, where)
        f.finish()
    return images


def _read_points_bin(path: Path) -> np.ndarray:
    """``[P, 3]`` float64 xyz; the track lengths are walked to find each record, the tracks skipped."""
    with _BinFile(path) as f:
        n = f.count("3D points", _POINT_HEAD_BYTES + 8)
        # a tight loop: only the track length of each record is read, to find the next one
        buf, size, off, unpack = f.buf, f.size, f.off, _U64.unpack_from
        starts: list[int] = []
        for i in range(n):
            if off + _POINT_HEAD_BYTES + 8 > size:
                f.off = off
                raise f.truncated(f"3D point record {i}")
            starts.append(off)
            off += _POINT_HEAD_BYTES + 8 + unpack(buf, off + _POINT_HEAD_BYTES)[0] * _TRACK_ELEMENT_BYTES
        if off > size:
            f.off = starts[-1]
            raise f.truncated(f"the track of 3D point {n - 1}")
        f.off = off
        f.finish()
        if n == 0:
            return np.zeros((0, 3))
        raw = np.frombuffer(f.buf, dtype=np.uint8)
        first = np.asarray(starts, dtype=np.int64)
        ids = raw[first[:, None] + np.arange(8)].view("<u8").reshape(n)
        byte_idx = (first + 8)[:, None] + np.arange(24)  # xyz follows the u64 id
        xyz = raw[byte_idx].view("<f8").reshape(n, 3).astype(np.float64)
        del raw  # release the view before the map closes
        _refuse_duplicate_points(ids, lambda k: f"{path}: 3D point record {k} (byte {starts[k]})")
        bad = ~(np.isfinite(xyz) & (np.abs(xyz) <= _F32_MAX)).all(axis=1)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise FileFormatError(f"{path}: non-finite 3D point coordinates (or beyond float32) in 3D point record "
                                  f"{k} (POINT3D_ID {int(ids[k])}, byte {starts[k]}): {xyz[k].tolist()}")
    return xyz


# ---------------------------------------------------------------------------------------------
# text files


#: the count COLMAP writes in a text file's header (``# Number of images: 8, mean ...``)
_INTEGER = re.compile(r"-?[0-9]+\Z")
_DECLARED = re.compile(r"#\s*Number of (cameras|images|points)\s*:\s*(\d+)", re.IGNORECASE)


def _text_lines(path: Path) -> tuple[list[tuple[int, str]], tuple[int, int] | None]:
    """``(line number, line)`` of every line that is not a comment (blank lines kept), and
    ``(line number, count)`` of the header's ``# Number of ...: N`` if it has one."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise FileFormatError(f"{path}: not a UTF-8 text file") from None
    except OSError as e:
        raise FileFormatError(f"{path}: cannot read the file ({e})") from None
    lines, declared = [], None
    for i, ln in enumerate(text.splitlines()):
        if ln.lstrip().startswith("#"):
            m = _DECLARED.match(ln.strip())
            if m and declared is None:
                declared = (i + 1, int(m.group(2)))
        else:
            lines.append((i + 1, ln.strip()))
    return lines, declared


def _check_declared(path: Path, declared: tuple[int, int] | None, found: int, what: str) -> None:
    """Refuse a file whose header declares another number of records than it holds."""
    if declared is not None and declared[1] != found:
        raise FileFormatError(f"{path}:{declared[0]}: the header declares {declared[1]} {what} but the file "
                              f"holds {found}: truncated or edited")


def _bad_line(path: Path, lineno: int, expected: str, line: str) -> FileFormatError:
    shown = line if len(line) <= 80 else line[:77] + "..."
    return FileFormatError(f"{path}:{lineno}: expected {expected}, got {shown!r}")


def _read_cameras_txt(path: Path) -> dict[int, _ColmapCamera]:
    cams: dict[int, _ColmapCamera] = {}
    expected = "CAMERA_ID MODEL WIDTH HEIGHT PARAMS..."
    lines, declared = _text_lines(path)
    for lineno, line in lines:
        if not line:
            continue
        parts = line.split()
        if len(parts) < 4 or parts[1] not in _PARAMS_BY_NAME:
            raise _bad_line(path, lineno, expected + " with a known COLMAP model", line)
        n_params = _PARAMS_BY_NAME[parts[1]]
        if len(parts) != 4 + n_params:
            raise _bad_line(path, lineno, f"{n_params} parameters for a {parts[1]} camera", line)
        try:
            cam_id = int(parts[0])
            cam = _ColmapCamera(parts[1], int(parts[2]), int(parts[3]), tuple(float(p) for p in parts[4:]),
                                f"{path}:{lineno}")
        except ValueError:
            raise _bad_line(path, lineno, expected, line) from None
        if cam_id in cams:
            raise FileFormatError(f"{path}:{lineno}: CAMERA_ID {cam_id} appears twice (first: {cams[cam_id].where})")
        cams[cam_id] = cam
    _check_declared(path, declared, len(cams), "cameras")
    return cams


def _is_points2d(line: str) -> bool:
    """Whether ``line`` is an image's POINTS2D line: ``X Y POINT3D_ID`` triples (empty: none)."""
    parts = line.split()
    if len(parts) % 3:
        return False
    try:
        np.asarray(parts[0::3] + parts[1::3], dtype=np.float64)
    except (ValueError, OverflowError):
        return False
    return all(_INTEGER.match(p) for p in parts[2::3])


def _read_images_txt(path: Path) -> dict[int, _ColmapImage]:
    """Images by IMAGE_ID. Each image is two lines: ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``
    and its POINTS2D line (``X Y POINT3D_ID`` triples, possibly empty; may be absent only after the
    last image). A second line that is not a POINTS2D line, a repeated IMAGE_ID and a count that differs
    from the header's are refused naming the line."""
    images: dict[int, _ColmapImage] = {}
    lines, declared = _text_lines(path)
    i = 0
    while i < len(lines):
        lineno, line = lines[i]
        i += 1
        if not line:
            continue
        parts = line.split(maxsplit=9)
        try:
            if len(parts) != 10:
                raise ValueError
            image_id = int(parts[0])
            q = tuple(float(v) for v in parts[1:5])
            t = tuple(float(v) for v in parts[5:8])
            image = _ColmapImage(q, t, int(parts[8]), parts[9], f"{path}:{lineno}")  # type: ignore[arg-type]
        except ValueError:
            raise _bad_line(path, lineno, "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME", line) from None
        if image_id in images:
            raise FileFormatError(f"{path}:{lineno}: IMAGE_ID {image_id} appears twice "
                                  f"(first: {images[image_id].where})")
        if i < len(lines):  # the POINTS2D line (its contents are not needed, its place is)
            points_no, points_line = lines[i]
            i += 1
            if not _is_points2d(points_line):
                raise _bad_line(path, points_no, f"the POINTS2D line (X Y POINT3D_ID ...; empty for none) of "
                                f"IMAGE_ID {image_id} (line {lineno}): every image takes two lines", points_line)
        images[image_id] = image
    _check_declared(path, declared, len(images), "images")
    return images


def _refuse_duplicate_points(ids: np.ndarray, where: Callable[[int], str]) -> None:
    """Refuse a repeated POINT3D_ID; ``where(k)`` describes record ``k`` (its file and byte)."""
    if ids.size < 2:
        return
    order = np.argsort(ids, kind="stable")
    same = np.flatnonzero(ids[order][1:] == ids[order][:-1])
    if same.size:
        first, again = sorted((int(order[same[0]]), int(order[same[0] + 1])))
        raise FileFormatError(f"{where(again)}: POINT3D_ID {int(ids[again])} appears twice (first: {where(first)})")


def _read_points_txt(path: Path) -> np.ndarray:
    xyz: list[tuple[float, float, float]] = []
    seen: dict[int, int] = {}  # POINT3D_ID -> line
    lines, declared = _text_lines(path)
    for lineno, line in lines:
        if not line:
            continue
        parts = line.split()
        try:
            if len(parts) < 8 or len(parts) % 2:
                raise ValueError
            point_id = int(parts[0])
            p = (float(parts[1]), float(parts[2]), float(parts[3]))
        except ValueError:
            raise _bad_line(path, lineno, "POINT3D_ID X Y Z R G B ERROR TRACK... (IMAGE_ID POINT2D_IDX pairs)",
                            line) from None
        if not all(abs(v) <= _F32_MAX for v in p):  # False for nan
            raise FileFormatError(f"{path}: non-finite 3D point coordinates (or beyond float32) at line {lineno}: "
                                  f"{list(p)}")
        xyz.append(p)
        if point_id in seen:
            raise FileFormatError(f"{path}:{lineno}: POINT3D_ID {point_id} appears twice (first: line {seen[point_id]})")
        seen[point_id] = lineno
    _check_declared(path, declared, len(xyz), "points")
    return np.asarray(xyz, dtype=np.float64).reshape(-1, 3)


def _model_file(sparse: Path, stem: str) -> Path | None:
    for ext in (".bin", ".txt"):
        p = sparse / (stem + ext)
        if p.is_file():
            return p
    return None


def _read_model(root: Path, sparse: Path) -> tuple[dict[int, _ColmapCamera], dict[int, _ColmapImage],
                                                   np.ndarray | None, Path]:
    """The model in ``sparse`` (whose files must lie inside ``root``, symlinks followed)."""
    cams_path, imgs_path = _model_file(sparse, "cameras"), _model_file(sparse, "images")
    if cams_path is None or imgs_path is None:
        missing = [s for s, p in (("cameras", cams_path), ("images", imgs_path)) if p is None]
        raise FileFormatError(f"{sparse}: COLMAP model incomplete: no {' or '.join(m + '.bin/.txt' for m in missing)}")
    pts_path = _model_file(sparse, "points3D")
    for p in (cams_path, imgs_path, pts_path):
        if p is not None:
            inside(root, str(p.relative_to(root)), str(p), "the model file")
    cams = (_read_cameras_bin if cams_path.suffix == ".bin" else _read_cameras_txt)(cams_path)
    imgs = (_read_images_bin if imgs_path.suffix == ".bin" else _read_images_txt)(imgs_path)
    pts = None if pts_path is None else (_read_points_bin if pts_path.suffix == ".bin" else _read_points_txt)(pts_path)
    return cams, imgs, pts, cams_path


# ---------------------------------------------------------------------------------------------
# cameras and poses


def qvec_to_rotation(qvec: Sequence[float]) -> torch.Tensor:
    """Rotation ``[3, 3]`` float64 of a quaternion ``(w, x, y, z)`` (normalised first, as COLMAP does)."""
    q = torch.as_tensor(qvec, dtype=torch.float64)
    big = q.abs().max()
    norm = big * torch.linalg.vector_norm(q / big) if torch.isfinite(q).all() and big > 0 else big
    if not torch.isfinite(q).all() or not norm >= 1e-12:
        raise InputValueError(f"qvec must be a finite non-zero quaternion (w, x, y, z), got {list(qvec)}")
    w, x, y, z = (q / norm).tolist()
    return torch.tensor([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ], dtype=torch.float64)


def _pinhole(cam: _ColmapCamera) -> tuple[tuple[float, float, float, float], tuple[float, ...] | None]:
    """``(fx, fy, cx, cy)`` and OpenCV ``(k1, k2, p1, p2, k3)`` (None when there is no distortion)."""
    p = cam.params
    if cam.model == "SIMPLE_PINHOLE":
        return (p[0], p[0], p[1], p[2]), None
    if cam.model == "PINHOLE":
        return (p[0], p[1], p[2], p[3]), None
    if cam.model == "SIMPLE_RADIAL":
        k, d = (p[0], p[0], p[1], p[2]), (p[3], 0.0, 0.0, 0.0, 0.0)
    elif cam.model == "RADIAL":
        k, d = (p[0], p[0], p[1], p[2]), (p[3], p[4], 0.0, 0.0, 0.0)
    else:  # OPENCV
        k, d = (p[0], p[1], p[2], p[3]), (p[4], p[5], p[6], p[7], 0.0)
    return k, (None if not any(d) else d)


def _scale_factor_ok(cam_w: int, cam_h: int, w: int, h: int) -> bool:
    """Whether ``w x h`` is ``cam_w x cam_h`` divided by one factor, each side rounded within 1 px."""
    lo = max((w - 1) / cam_w, (h - 1) / cam_h)
    hi = min((w + 1) / cam_w, (h + 1) / cam_h)
    return lo <= hi and hi > 0


def _frame(name: str, img: _ColmapImage, cam: _ColmapCamera, path: Path, size: tuple[int, int]) -> Frame:
    """The frame of image ``name``: pinhole camera scaled to the image file's ``size`` ``(w, h)``;
    every refusal names the model file and the line (text) or record (binary) of the image or camera."""
    if not all(math.isfinite(v) for v in cam.params) or cam.width < 1 or cam.height < 1:
        raise FileFormatError(f"{cam.where}: the camera of image {name!r} is invalid: {cam.model} "
                              f"{cam.width}x{cam.height} {list(cam.params)}")
    (fx, fy, cx, cy), dist = _pinhole(cam)
    if not (fx > 0 and fy > 0):
        raise FileFormatError(f"{cam.where}: the camera of image {name!r} has focal lengths {fx}, {fy} (must be > 0)")
    w, h = size
    if not _scale_factor_ok(cam.width, cam.height, w, h):
        raise FileFormatError(f"{path}: image is {w}x{h}, which is not its camera's {cam.width}x{cam.height} "
                              f"(in {cam.where}) divided by one factor")
    sx, sy = w / cam.width, h / cam.height
    k = torch.tensor([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    if not float32_finite(k):
        raise FileFormatError(f"{cam.where}: the camera of image {name!r} does not fit float32 (|value| > 3.4e38): "
                              f"{cam.model} {list(cam.params)}")
    w2c = torch.eye(4, dtype=torch.float64)
    try:
        w2c[:3, :3] = qvec_to_rotation(img.qvec)
    except InputValueError:
        raise FileFormatError(f"{img.where}: image {name!r} has a bad quaternion {list(img.qvec)}") from None
    w2c[:3, 3] = torch.tensor(img.tvec, dtype=torch.float64)
    if not torch.isfinite(w2c).all():
        raise FileFormatError(f"{img.where}: image {name!r} has a non-finite translation {list(img.tvec)}")
    if not float32_finite(w2c):
        raise FileFormatError(f"{img.where}: image {name!r} has a translation beyond float32 (|value| > 3.4e38) "
                              f"{list(img.tvec)}")
    camera = dataset_camera(f"{img.where}: image {name!r}", w2c.float(), k, w, h)
    return Frame(name, camera, path, dist)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# the dataparser


def _sparse_dir(root: Path) -> Path:
    for d in (root / "sparse" / "0", root / "sparse"):
        if _model_file(d, "cameras") is not None:
            return d
    raise FileFormatError(f"{root}: no COLMAP model: expected sparse/0/cameras.bin|txt (or sparse/cameras.bin|txt)")


def _image_paths(root: Path, folder: Path, by_name: dict[str, _ColmapImage]) -> dict[str, Path]:
    """The file of every image in ``folder``; :class:`FileFormatError` naming the model file's line
    (or record) for a name that is absolute or leads outside ``root`` (``..``, symlinks), before
    anything is opened."""
    return {nm: inside(root, nm, im.where, "image name", base=folder) for nm, im in by_name.items()}


def _pick_images_dir(root: Path, by_name: dict[str, _ColmapImage], resolution: int | None) -> Path:
    """``images``, or with ``resolution`` the most downscaled ``images_N`` whose every image exists and
    has a longer side of at least ``resolution`` pixels."""
    if resolution is not None:
        for n in _DOWNSCALED:
            d = root / f"images_{n}"
            if not d.is_dir():
                continue
            inside(root, d.name, str(root), "the images folder")
            files = _image_paths(root, d, by_name)
            if not all(p.is_file() for p in files.values()):
                continue
            try:
                if all(max(image_size(p)) >= resolution for p in files.values()):
                    return d
            except FileFormatError:
                continue
    return root / "images"


def read_colmap(root: str | Path, *, images: str | None = None, resolution: int | None = None, holdout: int = 8,
                background: Sequence[float] | torch.Tensor | None = None) -> SceneData:
    """Read a COLMAP scene: ``root/sparse/0/`` (or ``root/sparse/``) and the images beside it.

    Args:
        root: the scene folder (holding ``sparse/`` and ``images/``).
        images: the images folder under ``root`` (``"images"``, or Mip-NeRF 360's ``"images_2"``,
            ``"images_4"``, ``"images_8"``). None: ``images``, or with ``resolution`` the most downscaled
            ``images_N`` whose images are still at least that large.
        resolution: the working resolution (longer side, pixels) the views will be taken at; it only
            chooses the folder here (pass it to :meth:`SceneData.views` as well).
        holdout: every ``holdout``-th frame by sorted image name (index 0, 8, 16, ...) is a test view,
            as 3DGS's ``--eval``; 0: every frame is a training view.
        background: ``[3]`` sRGB colour that RGBA images are composited over (default black).

    Returns:
        :class:`SceneData` with format ``"colmap"``; ``points`` = ``points3D`` xyz ``[P, 3]`` float32,
        or None if the model has no points file. Cameras are at the size of the image files read.

    Raises:
        FileFormatError: a missing, truncated or foreign model file, a repeated IMAGE_ID,
            CAMERA_ID or POINT3D_ID, an images file without its POINTS2D lines, a camera model that is
            not pinhole, SIMPLE_RADIAL, RADIAL or OPENCV, missing image files, an image whose size does
            not match its camera, values beyond float32, or a path (image name, images folder, model
            file) that leads outside ``root``, symlinks included; each names the file and its line
            (text) or record (binary).
        InputValueError: a bad argument.
    """
    root = Path(root)
    if isinstance(holdout, bool) or not isinstance(holdout, int) or holdout < 0:
        raise InputValueError(f"holdout must be an int >= 0 (every holdout-th view is a test view), got {holdout!r}")
    if resolution is not None and (isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 2):
        raise InputValueError(f"resolution must be an int >= 2 (longer side in pixels), got {resolution!r}")
    if images is not None and (not isinstance(images, str) or not images or Path(images).is_absolute()
                               or ".." in Path(images).parts):
        raise InputValueError(f"images must be the name of a folder under the scene root, got {images!r}")
    bg = torch.zeros(3) if background is None else torch.as_tensor(background, dtype=torch.float32).flatten()
    if bg.numel() != 3 or not torch.isfinite(bg).all():
        raise InputValueError(f"background must be 3 finite sRGB values, got {background!r}")
    if not root.is_dir():
        raise FileFormatError(f"{root}: scene folder not found")

    sparse = _sparse_dir(root)
    cams, imgs, pts, model_file = _read_model(root, sparse)
    by_name: dict[str, _ColmapImage] = {}
    for im in imgs.values():
        if im.name in by_name:
            raise FileFormatError(f"{im.where}: image name {im.name!r} appears twice in the images file "
                                  f"(first: {by_name[im.name].where})")
        by_name[im.name] = im
    names = sorted(by_name)
    for nm in names:
        cam_id = by_name[nm].camera_id
        if cam_id not in cams:
            raise FileFormatError(f"{by_name[nm].where}: image {nm!r} refers to camera {cam_id}, which is not in "
                                  f"the file {model_file}")
        model = cams[cam_id].model
        if model not in _SUPPORTED:
            raise FileFormatError(
                f"{cams[cam_id].where}: camera {cam_id} (image {nm!r}) uses the {model} model; this reader takes "
                f"{', '.join(_SUPPORTED)}: run COLMAP's image_undistorter on the scene and read its output")

    img_dir = root / images if images is not None else _pick_images_dir(root, by_name, resolution)
    if not img_dir.is_dir():
        raise FileFormatError(f"{img_dir}: images folder not found")
    inside(root, str(img_dir.relative_to(root)), str(root), "the images folder")
    files = _image_paths(root, img_dir, by_name)
    missing = [nm for nm in names if not files[nm].is_file()]
    if missing:
        raise FileFormatError(f"{img_dir}: {len(missing)} of the {len(names)} images in {model_file.parent} are "
                              f"missing (first: {', '.join(missing[:5])}), the first listed at {by_name[missing[0]].where}")

    frames = [_frame(nm, by_name[nm], cams[by_name[nm].camera_id], files[nm], image_size(files[nm]))
              for nm in names]
    test = [f for i, f in enumerate(frames) if holdout and i % holdout == 0]
    train = [f for i, f in enumerate(frames) if not (holdout and i % holdout == 0)]
    points = None if pts is None else torch.from_numpy(pts.astype(np.float32))
    return SceneData({"train": train, "test": test}, points=points, background=bg, source=str(root), format="colmap")
