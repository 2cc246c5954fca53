"""Run-time XR state and the pinhole camera used to place anchors on screen.

Conventions (see docs/conventions.md): OpenCV camera axes (x right, y down, z forward); pixel
centres at (i + 0.5); normalised screen coordinates in [-1, 1] about the optical centre with the
pixel-centre convention (``align_corners=False``): ``x_n = 2 * u / W - 1`` for continuous pixel
coordinate ``u``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch

from .checks import check_tensor
from .errors import InputValueError, StateError

__all__ = ["RuntimeState", "Camera"]


@dataclass(frozen=True)
class RuntimeState:
    """What the headset does to the image at run time.

    Attributes:
        downsample: d = native rendering resolution S / display sampling rate, >= 1 (continuous).
        power_saving: rho = 1 - P_target / P_ref, in [0, 1).
        gaze: gaze point in normalised screen coordinates ``(x, y)`` in [-1, 1]^2, or None.
    """

    downsample: float = 1.0
    power_saving: float = 0.0
    gaze: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        d, rho = float(self.downsample), float(self.power_saving)
        if not math.isfinite(d) or d < 1.0:
            raise StateError(f"downsample must be a finite number >= 1 (S / display rate), got {self.downsample!r}")
        if not math.isfinite(rho) or not (0.0 <= rho < 1.0):
            raise StateError(f"power_saving must be a finite number in [0, 1), got {self.power_saving!r}")
        object.__setattr__(self, "downsample", d)
        object.__setattr__(self, "power_saving", rho)
        if self.gaze is not None:
            g = tuple(float(v) for v in self.gaze)
            if len(g) != 2 or not all(math.isfinite(v) and -1.0 <= v <= 1.0 for v in g):
                raise StateError(f"gaze must be None or (x, y) in [-1, 1]^2, got {self.gaze!r}")
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
        check_tensor("world_to_camera", self.world_to_camera, [4, 4], finite=True)
        check_tensor("intrinsics", self.intrinsics, [3, 3], finite=True)
        if int(self.width) < 1 or int(self.height) < 1:
            raise InputValueError(f"width and height must be >= 1, got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates, ``[3]``."""
        r, t = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return -(r.transpose(0, 1) @ t)

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``round(size / factor)`` pixels (intrinsics rescaled exactly)."""
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
        """World points ``[N, 3]`` -> (pixel coords ``[N, 2]``, depth ``[N]``). Depth <= 0 is behind."""
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
        world-to-camera, ``FoVx``/``FoVy`` in radians, ``image_width``/``image_height``)."""
        w2c = viewpoint_camera.world_view_transform.detach().transpose(0, 1).float().cpu()
        w, h = int(viewpoint_camera.image_width), int(viewpoint_camera.image_height)
        fx = w / (2.0 * math.tan(float(viewpoint_camera.FoVx) / 2.0))
        fy = h / (2.0 * math.tan(float(viewpoint_camera.FoVy) / 2.0))
        k = torch.tensor([[fx, 0.0, w / 2.0], [0.0, fy, h / 2.0], [0.0, 0.0, 1.0]])
        return cls(w2c, k, w, h)
