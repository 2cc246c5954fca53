"""Run-time XR state and the pinhole camera used to place anchors on screen.

Conventions (see docs/reference/conventions.md): OpenCV camera axes (x right, y down, z forward); pixel
centres at (i + 0.5); normalised screen coordinates in [-1, 1] about the optical centre with the
pixel-centre convention (``align_corners=False``): ``x_n = 2 * u / W - 1`` for continuous pixel
coordinate ``u``.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Any

import torch

from .checks import brief, check_number, check_tensor
from .errors import InputValueError, StateRangeError

__all__ = ["RuntimeState", "Camera"]


#: largest image side in pixels: pixel coordinates stay exact integers in float32 up to 2^24
MAX_PIXELS = 1 << 24
#: focal lengths are refused outside [size / FOCAL_RATIO, size * FOCAL_RATIO] pixels (``size`` the image
#: side): the field of view then lies in [2e-6, pi - 4e-6] rad, representable in float32, and the
#: projection of a point in view stays far from float32 overflow
FOCAL_RATIO = 1e6


def _real(name: str, value: Any, error: type[InputValueError] = InputValueError) -> float:
    """``value`` as a float if it is a real number (a Python/NumPy number or a 0-d tensor, not a
    bool or a string), else ``error`` naming ``name``. An int beyond float range gives +-inf (the
    callers' range checks refuse it)."""
    if isinstance(value, torch.Tensor) and value.numel() == 1 and not value.is_complex():
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise error(f"{name} must be a real number, got {brief(value)} ({type(value).__name__})")
    try:
        return float(value)
    except OverflowError:
        return -math.inf if value < 0 else math.inf
    except (ValueError, TypeError, ArithmeticError):
        raise error(f"{name} must be a real number, got {brief(value)} ({type(value).__name__})") from None


def _positive_int(name: str, value: Any) -> int:
    """An int in [1, :data:`MAX_PIXELS`] (an image side in pixels), else InputValueError naming ``name``."""
    if isinstance(value, torch.Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < 1:
        raise InputValueError(f"{name} must be an int >= 1 (pixels), got {brief(value)}")
    if int(value) > MAX_PIXELS:
        raise InputValueError(f"{name} must be an int <= {MAX_PIXELS} (pixels), got {brief(value)}")
    return int(value)


def _nonnegative_int(name: str, value: Any) -> int:
    """An int in [0, 2^63) (an index), else InputValueError naming ``name``."""
    if isinstance(value, torch.Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < 0:
        raise InputValueError(f"{name} must be an int >= 0, got {brief(value)}")
    if int(value) >= 2**63:
        raise InputValueError(f"{name} must be an int < 2^63 (an int64 index), got {brief(value)}")
    return int(value)


@dataclass(frozen=True)
class RuntimeState:
    """What the headset does to the image at run time.

    Attributes:
        downsample: d = native rendering resolution S / display sampling rate, >= 1 (continuous).
        power_saving: rho = 1 - P_target / P_ref, in [0, 1).
        gaze: gaze direction ``(azimuth, elevation)`` in degrees from the lens axis (x right, y down as the
            display: positive elevation looks down), each in (-90, 90), or None (no eye tracking).
            Whether it lies in a lens's field is checked where the lens is known (the foveation stage
            and schedule).
    """

    downsample: float = 1.0
    power_saving: float = 0.0
    gaze: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        d, rho = _real("downsample", self.downsample, StateRangeError), _real("power_saving", self.power_saving, StateRangeError)
        if not math.isfinite(d) or d < 1.0:
            raise StateRangeError(f"downsample must be a finite number >= 1 (S / display rate), got {brief(self.downsample)}")
        if not math.isfinite(rho) or not (0.0 <= rho < 1.0):
            raise StateRangeError(f"power_saving must be a finite number in [0, 1), got {brief(self.power_saving)}")
        object.__setattr__(self, "downsample", d)
        object.__setattr__(self, "power_saving", rho)
        if self.gaze is not None:
            gaze = self.gaze.tolist() if isinstance(self.gaze, torch.Tensor) else self.gaze
            if isinstance(gaze, (str, bytes)) or not isinstance(gaze, (tuple, list)) or len(gaze) != 2:
                raise StateRangeError(f"gaze must be None or a pair (azimuth, elevation) in degrees, got {brief(self.gaze)}")
            g = tuple(_real("gaze", v, StateRangeError) for v in gaze)
            if not all(math.isfinite(v) and -90.0 < v < 90.0 for v in g):
                raise StateRangeError(f"gaze must be None or (azimuth, elevation) in (-90, 90) degrees, got {brief(self.gaze)}")
            object.__setattr__(self, "gaze", g)


@dataclass
class Camera:
    """Pinhole camera.

    Attributes:
        world_to_camera: ``[4, 4]`` rigid transform, OpenCV axes.
        intrinsics: ``[3, 3]`` with fx, fy, cx, cy in pixels (pixel centres at i + 0.5).
        width, height: image size in pixels at which ``intrinsics`` hold.
    """

    world_to_camera: torch.Tensor
    intrinsics: torch.Tensor
    width: int
    height: int
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.width, self.height = _positive_int("width", self.width), _positive_int("height", self.height)
        for name, t in (("world_to_camera", self.world_to_camera), ("intrinsics", self.intrinsics)):
            if isinstance(t, torch.Tensor) and t.is_meta:
                raise InputValueError(f"{name} is on the meta device, which holds no values")
        check_tensor("world_to_camera", self.world_to_camera, [4, 4], finite=True)
        check_tensor("intrinsics", self.intrinsics, [3, 3], finite=True)
        if not self.world_to_camera.is_floating_point() or not self.intrinsics.is_floating_point():
            raise InputValueError(f"world_to_camera and intrinsics must be floating-point, got "
                                  f"{self.world_to_camera.dtype} and {self.intrinsics.dtype}")
        _check_intrinsics(self.intrinsics.detach().double().cpu(), self.width, self.height)
        _check_rigid(self.world_to_camera.detach().double().cpu())
        if float(self.world_to_camera.detach().double().abs().max()) > torch.finfo(torch.float32).max:
            raise InputValueError("world_to_camera holds values beyond float32 (|value| > 3.4e38); the "
                                  "renderers compute in float32")

    @property
    def fov(self) -> tuple[float, float]:
        """Horizontal and vertical field of view in radians, each in [2e-6, pi - 4e-6] (:data:`FOCAL_RATIO`)."""
        k = self.intrinsics
        return (2.0 * math.atan(self.width / (2.0 * float(k[0, 0]))), 2.0 * math.atan(self.height / (2.0 * float(k[1, 1]))))

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates, ``[3]``."""
        r, t = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return -(r.transpose(0, 1) @ t)

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``round(size / factor)`` pixels (intrinsics rescaled exactly); ``factor``
        a finite number > 0."""
        factor = check_number("factor", factor, low=0.0, low_open=True)
        if not max(self.width, self.height) / factor <= MAX_PIXELS + 0.5:
            raise InputValueError(f"factor {factor:g} would give an image side over {MAX_PIXELS} pixels "
                                  f"(from {self.width}x{self.height})")
        w, h = max(1, round(self.width / factor)), max(1, round(self.height / factor))
        k = self.intrinsics.clone()
        k[0] *= w / self.width
        k[1] *= h / self.height
        return Camera(self.world_to_camera, k, w, h, dict(self.extra))

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """World points ``[N, 3]`` -> camera-space points ``[N, 3]``."""
        w2c = self.world_to_camera.to(points)
        return points @ w2c[:3, :3].transpose(0, 1) + w2c[:3, 3]

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World points ``[N, 3]`` -> (pixel coords ``[N, 2]``, depth ``[N]``). Depth <= 0 is behind.

        The pinhole division by the depth applies on both sides of the camera: a point behind it, at
        camera coordinates ``(x, y, -z)``, lands where ``(x, y, z)`` does, mirrored through the principal
        point; only ``|depth| < 1e-12`` is divided as ``1e-12`` (finite pixel coordinates, never inf)."""
        pc = self.to_camera(points)
        z = pc[:, 2]
        k = self.intrinsics.to(points)
        zs = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
        uv = torch.stack([k[0, 0] * pc[:, 0] / zs + k[0, 2], k[1, 1] * pc[:, 1] / zs + k[1, 2]], dim=-1)
        return uv, z

    def normalized_screen(self, points: torch.Tensor) -> torch.Tensor:
        """World points ``[N, 3]`` -> normalised screen coordinates ``[N, 2]`` about the image centre
        (the lens's optical centre), [-1, 1] inside the image. Points behind the camera get +inf."""
        # one affine map [R, 3] -> (x_n z, y_n z, z) folds pixel scaling into the projection (this runs
        # per frame on every visible anchor: 4x faster than project() followed by rescaling)
        pixels_to_screen = torch.tensor([[2.0 / self.width, 0.0, -1.0], [0.0, 2.0 / self.height, -1.0], [0.0, 0.0, 1.0]],
                                        dtype=points.dtype, device=points.device)
        m = pixels_to_screen @ self.intrinsics.to(points) @ self.world_to_camera.to(points)[:3]  # [3, 4]
        pc = torch.addmm(m[:, 3], points, m[:, :3].transpose(0, 1))  # [N, 3]
        z = pc[:, 2:]
        return (pc[:, :2] / z).masked_fill_(z <= 0, float("inf"))

    @classmethod
    def from_scaffold(cls, viewpoint_camera: Any) -> "Camera":
        """Convert a Scaffold-GS / 3DGS ``Camera`` (``world_view_transform`` is the transposed
        world-to-camera, ``FoVx``/``FoVy`` in radians, ``image_width``/``image_height``; principal
        point at the image centre ``(w/2, h/2)`` as its projection matrix puts it). Its ``uid`` (the
        training-camera index that picks the appearance code) goes to ``extra["uid"]``."""
        w2c = viewpoint_camera.world_view_transform.detach().transpose(0, 1).float().cpu()
        w = _positive_int("image_width", viewpoint_camera.image_width)
        h = _positive_int("image_height", viewpoint_camera.image_height)
        fovs = [_real(n, getattr(viewpoint_camera, n)) for n in ("FoVx", "FoVy")]
        for name, fov in zip(("FoVx", "FoVy"), fovs):
            if not (math.isfinite(fov) and 0.0 < fov < math.pi):
                raise InputValueError(f"{name} must be a field of view in (0, pi) radians, got {fov!r}")
        focals = []
        for name, n, fov in zip(("FoVx", "FoVy"), (w, h), fovs):
            half = math.tan(fov / 2.0)  # 0 for a subnormal fov
            f = n / (2.0 * half) if half > 0 else math.inf
            if not n / FOCAL_RATIO <= f <= n * FOCAL_RATIO:
                raise InputValueError(f"{name} = {fov!r} rad gives a focal length of {f:g} px for {n} px, outside "
                                      f"[{n / FOCAL_RATIO:g}, {n * FOCAL_RATIO:g}] (see Camera's intrinsics)")
            focals.append(f)
        fx, fy = focals
        k = torch.tensor([[fx, 0.0, w / 2.0], [0.0, fy, h / 2.0], [0.0, 0.0, 1.0]])
        uid = getattr(viewpoint_camera, "uid", None)
        return cls(w2c, k, w, h, {} if uid is None else {"uid": _nonnegative_int("uid", uid)})


def _check_intrinsics(k: torch.Tensor, width: int, height: int) -> None:
    """A pinhole ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` (float64 CPU copy) with fx in
    ``[width, width * FOCAL_RATIO^2] / FOCAL_RATIO`` and fy likewise with ``height`` (pixels)."""
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise InputValueError(f"intrinsics: focal lengths fx = K[0, 0] and fy = K[1, 1] must be > 0 (pixels), "
                              f"got fx = {float(k[0, 0]):g}, fy = {float(k[1, 1]):g}")
    for name, f, size, side in (("fx = K[0, 0]", float(k[0, 0]), width, "width"), ("fy = K[1, 1]", float(k[1, 1]), height, "height")):
        if not size / FOCAL_RATIO <= f <= size * FOCAL_RATIO:
            raise InputValueError(
                f"intrinsics: focal length {name} must be in [{size / FOCAL_RATIO:g}, {size * FOCAL_RATIO:g}] pixels "
                f"({side} {size} / {FOCAL_RATIO:g} to {side} x {FOCAL_RATIO:g}: a field of view in (0, pi) that the "
                f"projection represents), got {f:g}")
    if abs(float(k[2, 2]) - 1.0) > 1e-6 or bool(k[2, :2].abs().max() > 1e-9) or abs(float(k[1, 0])) > 1e-9:
        raise InputValueError(f"intrinsics must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {k.tolist()}")


def _check_rigid(w2c: torch.Tensor, tol: float = 1e-3) -> None:
    """A rigid world-to-camera: rotation block orthonormal with det +1, last row ``[0, 0, 0, 1]``."""
    if bool((w2c[3] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=w2c.dtype)).abs().max() > 1e-6):
        raise InputValueError(f"world_to_camera: last row must be [0, 0, 0, 1], got {w2c[3].tolist()}")
    r = w2c[:3, :3]
    err = float((r @ r.T - torch.eye(3, dtype=r.dtype)).abs().max())
    if err > tol or float(torch.linalg.det(r)) < 0:
        raise InputValueError(f"world_to_camera: the rotation block must be orthonormal with determinant +1 "
                              f"(a rigid transform, no scale or mirror), got R R^T - I up to {err:.3g}, "
                              f"det {float(torch.linalg.det(r)):.4g}")
