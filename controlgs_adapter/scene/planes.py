"""Textured planes and their exact, anti-aliased rendering by ray casting.

A pixel is the box average of ``samples x samples`` stratified sub-samples; each sub-sample casts
one ray, takes the nearest plane hit, and looks the texture up trilinearly in a mip pyramid whose
level follows the sub-sample's analytic texture footprint (so a plane seen at a grazing angle
does not alias either). Colours are averaged in sRGB, as the renderer and the resampling stage do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from ..checks import check_tensor
from ..errors import InputValueError
from ..state import Camera
from .textures import load_texture, mip_pyramid

__all__ = ["TexturedPlane", "render_planes", "plane_points"]


@dataclass
class TexturedPlane:
    """A rectangle carrying a photograph.

    Attributes:
        name: label.
        center: ``[3]`` world position of the rectangle's centre.
        right: ``[3]`` vector from the centre to the middle of the right edge (texture +x).
        down: ``[3]`` vector from the centre to the middle of the bottom edge (texture +y), orthogonal to ``right``.
        texture: sRGB ``[3, Ht, Wt]`` in [0, 1], row 0 at the top edge.
        repeat: how many times the texture tiles across the plane in x and y.
    """

    name: str
    center: torch.Tensor
    right: torch.Tensor
    down: torch.Tensor
    texture: torch.Tensor
    repeat: tuple[int, int] = (1, 1)
    levels: list[torch.Tensor] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for n in ("center", "right", "down"):
            check_tensor(n, getattr(self, n), [3], finite=True)
            setattr(self, n, getattr(self, n).to(torch.float64))
        check_tensor("texture", self.texture, [3, "H", "W"], finite=True)
        if abs(float(self.right @ self.down)) > 1e-9 * float(self.right.norm() * self.down.norm()):
            raise InputValueError(f"plane {self.name!r}: right and down must be orthogonal")
        if len(self.repeat) != 2 or min(int(r) for r in self.repeat) < 1:
            raise InputValueError(f"plane {self.name!r}: repeat must be two integers >= 1, got {self.repeat!r}")
        self.repeat = (int(self.repeat[0]), int(self.repeat[1]))
        self.texture = self.texture.to(torch.float64)
        self.levels = mip_pyramid(self.texture)

    @classmethod
    def make(cls, name: str, texture: str, center: tuple[float, float, float], width: float, height: float,
             yaw_deg: float = 0.0, pitch_deg: float = 0.0, repeat: tuple[int, int] = (1, 1)) -> "TexturedPlane":
        """A ``width x height`` plane facing +z (world y up), turned by ``pitch_deg`` about its
        horizontal axis and then by ``yaw_deg`` about world y; carries ``skimage.data.<texture>``."""
        ry, rx = math.radians(yaw_deg), math.radians(pitch_deg)
        rot_y = torch.tensor([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]], dtype=torch.float64)
        rot_x = torch.tensor([[1, 0, 0], [0, math.cos(rx), -math.sin(rx)], [0, math.sin(rx), math.cos(rx)]], dtype=torch.float64)
        rot = rot_y @ rot_x
        right = rot @ torch.tensor([width / 2, 0.0, 0.0], dtype=torch.float64)
        down = rot @ torch.tensor([0.0, -height / 2, 0.0], dtype=torch.float64)
        return cls(name, torch.tensor(center, dtype=torch.float64), right, down, load_texture(texture), repeat)

    @property
    def normal(self) -> torch.Tensor:
        """Unit normal ``[3]``, ``right x down`` (points away from a viewer who sees the texture unmirrored)."""
        n = torch.linalg.cross(self.right, self.down)
        return n / n.norm()

    def sample(self, a: torch.Tensor, b: torch.Tensor, lod: torch.Tensor) -> torch.Tensor:
        """Trilinear texture lookup at plane coordinates ``a, b`` ``[M]`` in [-1, 1] (pixel-centre
        convention; the texture tiles ``repeat`` times) and mip level ``lod`` ``[M]`` -> sRGB ``[M, 3]``."""
        if self.repeat != (1, 1):
            a = torch.remainder((a + 1.0) * (self.repeat[0] / 2.0), 1.0) * 2.0 - 1.0
            b = torch.remainder((b + 1.0) * (self.repeat[1] / 2.0), 1.0) * 2.0 - 1.0
        top = len(self.levels) - 1
        lod = lod.clamp(0.0, float(top))
        l0 = lod.floor().long().clamp(max=top)
        frac = (lod - l0).unsqueeze(-1)
        grid = torch.stack([a, b], dim=-1).view(1, 1, -1, 2)
        out = torch.empty(a.shape[0], 3, dtype=torch.float64)

        def lookup(level: int, idx: torch.Tensor) -> torch.Tensor:
            tex = self.levels[level].unsqueeze(0)
            g = grid[:, :, idx]
            return F.grid_sample(tex, g, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0].T

        for level in torch.unique(l0).tolist():
            idx = (l0 == level).nonzero().squeeze(-1)
            lo = lookup(level, idx)
            hi = lookup(min(level + 1, top), idx) if level < top else lo
            out[idx] = lo + frac[idx] * (hi - lo)
        return out


def _matmul(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """``x @ m`` for tall ``x`` ``[M, K]`` and tiny ``m`` ``[K, J]`` by broadcasting (BLAS calls on such
    shapes are slow on a loaded machine)."""
    return (x.unsqueeze(-1) * m).sum(dim=-2)


def _sample_rays(camera: Camera, samples: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stratified sub-pixel rays: origin ``[3]``, directions ``[M, 3]`` (camera z = 1, so the ray
    parameter is the z-depth), and the direction's derivatives per sub-sample step in u and v ``[3]``."""
    k = camera.intrinsics.to(torch.float64)
    r = camera.world_to_camera[:3, :3].to(torch.float64)
    offs = (torch.arange(samples, dtype=torch.float64) + 0.5) / samples  # float64: u, v below promote to it
    u = (torch.arange(camera.width)[:, None] + offs).reshape(-1)  # [W*n]
    v = (torch.arange(camera.height)[:, None] + offs).reshape(-1)  # [H*n]
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    dc = torch.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], torch.ones_like(uu)], dim=-1).reshape(-1, 3)
    d = _matmul(dc, r)  # R^T dc for row vectors, [M, 3]
    du = r[0] / (k[0, 0] * samples)
    dv = r[1] / (k[1, 1] * samples)
    return camera.center.to(torch.float64), d, du, dv


def _window(plane: TexturedPlane, camera: Camera, n: int) -> torch.Tensor | None:
    """Flat indices of the sub-samples inside the bounding box of the plane's projection (a margin
    of one sub-sample), or None (all) when a corner is not in front of the camera."""
    corners = torch.stack([plane.center + sa * plane.right + sb * plane.down for sa in (-1, 1) for sb in (-1, 1)])
    pc = corners @ camera.world_to_camera[:3, :3].double().T + camera.world_to_camera[:3, 3].double()
    if bool((pc[:, 2] <= 1e-6).any()):
        return None
    k = camera.intrinsics.double()
    u = (k[0, 0] * pc[:, 0] / pc[:, 2] + k[0, 2]) * n
    v = (k[1, 1] * pc[:, 1] / pc[:, 2] + k[1, 2]) * n
    wn, hn = camera.width * n, camera.height * n
    c0, c1 = max(0, int(math.floor(float(u.min()))) - 1), min(wn, int(math.ceil(float(u.max()))) + 1)
    r0, r1 = max(0, int(math.floor(float(v.min()))) - 1), min(hn, int(math.ceil(float(v.max()))) + 1)
    if c0 >= c1 or r0 >= r1:
        return torch.zeros(0, dtype=torch.long)
    return (torch.arange(r0, r1)[:, None] * wn + torch.arange(c0, c1)).reshape(-1)


def render_planes(planes: list[TexturedPlane], camera: Camera, *, samples: int = 4,
                  background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Render ``planes`` seen by ``camera``, anti-aliased with ``samples x samples`` sub-samples per pixel.

    Returns:
        image: sRGB ``[3, H, W]`` float64 in [0, 1].
        coverage: ``[1, H, W]`` fraction of each pixel covered by some plane.
        depth: ``[1, H, W]`` mean camera z-depth of the covered sub-samples (0 where uncovered).
    """
    if int(samples) < 1:
        raise InputValueError(f"samples must be >= 1, got {samples!r}")
    n = int(samples)
    origin, d, du, dv = _sample_rays(camera, n)
    m = d.shape[0]
    best_t = torch.full((m,), math.inf, dtype=torch.float64)
    color = torch.tensor(background, dtype=torch.float64).expand(m, 3).clone()
    for plane in planes:
        flat = _window(plane, camera, n)  # [Mw] sub-samples the plane can cover
        if flat is not None and flat.numel() == 0:
            continue
        dw = d if flat is None else d[flat]
        nrm = plane.normal
        denom = _matmul(dw, nrm[:, None])[:, 0]  # [Mw]
        t = ((plane.center - origin) @ nrm) / torch.where(denom.abs() < 1e-15, torch.full_like(denom, 1e-15), denom)
        rel = origin + t[:, None] * dw - plane.center  # [Mw, 3]
        ab = _matmul(rel, torch.stack([plane.right / plane.right.dot(plane.right),
                                       plane.down / plane.down.dot(plane.down)], dim=-1))  # [Mw, 2]
        a, b = ab[:, 0], ab[:, 1]
        hit = (t > 1e-9) & (a.abs() <= 1.0) & (b.abs() <= 1.0) & (t < (best_t if flat is None else best_t[flat]))
        if not bool(hit.any()):
            continue
        local = hit.nonzero().squeeze(-1)
        th, dh, dnh, a, b = t[local], dw[local], denom[local], a[local], b[local]
        idx = local if flat is None else flat[local]
        # footprint: dp = t (dd - (n.dd / n.d) d) for a step dd of the ray direction
        h, w = plane.texture.shape[-2:]
        scale = torch.tensor([w * plane.repeat[0] / 2.0, h * plane.repeat[1] / 2.0], dtype=torch.float64)
        axes = torch.stack([plane.right / plane.right.dot(plane.right), plane.down / plane.down.dot(plane.down)], dim=-1)
        feet = []
        for dd in (du, dv):
            dp = th[:, None] * (dd - (dd @ nrm / dnh)[:, None] * dh)  # [Mh, 3]
            feet.append((_matmul(dp, axes) * scale).norm(dim=-1))
        lod = torch.log2(torch.stack(feet).amax(dim=0))  # [Mh]; sample() clamps it to the mip range (0 for -inf)
        color[idx] = plane.sample(a, b, lod)
        best_t[idx] = th
    hw = (camera.height, n, camera.width, n)
    covered = torch.isfinite(best_t)
    image = color.T.reshape(3, *hw).mean(dim=(2, 4))
    coverage = covered.to(torch.float64).reshape(1, *hw).mean(dim=(2, 4))
    depth_sum = torch.where(covered, best_t, torch.zeros_like(best_t)).reshape(1, *hw).sum(dim=(2, 4))
    count = covered.to(torch.float64).reshape(1, *hw).sum(dim=(2, 4))
    depth = depth_sum / count.clamp(min=1.0)
    return image.clamp(0.0, 1.0), coverage, depth


def plane_points(plane: TexturedPlane, spacing: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Points on a regular grid of ``spacing`` (world units) over the plane, with the texture's colour
    there: ``(xyz [P, 3], rgb [P, 3])``, float64."""
    if not spacing > 0:
        raise InputValueError(f"spacing must be > 0, got {spacing!r}")
    na = max(1, int(math.ceil(2 * float(plane.right.norm()) / spacing)))
    nb = max(1, int(math.ceil(2 * float(plane.down.norm()) / spacing)))
    a = (torch.arange(na, dtype=torch.float64) + 0.5) / na * 2 - 1
    b = (torch.arange(nb, dtype=torch.float64) + 0.5) / nb * 2 - 1
    bb, aa = torch.meshgrid(b, a, indexing="ij")
    aa, bb = aa.reshape(-1), bb.reshape(-1)
    xyz = plane.center + aa[:, None] * plane.right + bb[:, None] * plane.down
    texels = float(plane.texture.shape[-1]) * plane.repeat[0] / na  # one point covers about this many texels
    rgb = plane.sample(aa, bb, torch.full_like(aa, math.log2(max(texels, 1.0))))
    return xyz, rgb
