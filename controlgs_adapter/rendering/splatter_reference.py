"""Brute-force float64 Gaussian splatter: the test oracle for ``controlgs_adapter.rendering.splatter.rasterize``.

Written independently of the fast path (gsplat ``_torch_impl`` style): explicit 3x3 matrices and
``torch.linalg``, every pixel against every Gaussian (a dense ``[H*W, N]`` tensor, so only for small
scenes), and the compositing as the sequential per-splat loop of the 3DGS CUDA kernel. It shares
only the numeric conventions (the constants) with the fast path. Differentiable by autograd.
"""

from __future__ import annotations

import torch

from controlgs_adapter.state import Camera

from controlgs_adapter.rendering.splatter import (
    ALPHA_MAX,
    ALPHA_MIN,
    EXTENT_SIGMAS,
    FRUSTUM_MARGIN,
    LOW_PASS,
    NEAR_PLANE,
    TRANSMITTANCE_MIN,
    RasterOutput,
)

__all__ = ["rasterize_reference"]


def _rotation_matrix(q: torch.Tensor) -> torch.Tensor:
    """``[N, 4]`` (w, x, y, z) -> ``[N, 3, 3]`` via the matrix form ``(w^2 - v.v) I + 2 v v^T + 2 w [v]_x``."""
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, v = q[:, 0], q[:, 1:]
    eye = torch.eye(3, dtype=q.dtype, device=q.device).expand(q.shape[0], 3, 3)
    zero = torch.zeros_like(w)
    cross = torch.stack(
        [zero, -v[:, 2], v[:, 1], v[:, 2], zero, -v[:, 0], -v[:, 1], v[:, 0], zero], dim=-1
    ).reshape(-1, 3, 3)
    return (w * w - (v * v).sum(-1))[:, None, None] * eye + 2 * v[:, :, None] * v[:, None, :] + 2 * w[:, None, None] * cross


def rasterize_reference(
    means: torch.Tensor,
    scales: torch.Tensor,
    rotations: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | None = None,
    *,
    transmittance_min: float = TRANSMITTANCE_MIN,
) -> RasterOutput:
    """Same contract and conventions as ``rasterize`` (see its docstring), computed in float64 by
    brute force. Returns float64 tensors. Memory O(H W N): keep scenes small."""
    f64 = torch.float64
    means, scales, rotations, opacities, colors = (t.to(f64) for t in (means, scales, rotations, opacities, colors))
    n, width, height = means.shape[0], camera.width, camera.height
    w2c = camera.world_to_camera.to(f64)
    k = camera.intrinsics.to(f64)
    rot_wc, t_wc = w2c[:3, :3], w2c[:3, 3]

    p = (rot_wc @ means.unsqueeze(-1)).squeeze(-1) + t_wc  # [N, 3]
    z = p[:, 2]
    in_front = z > NEAR_PLANE
    zs = torch.where(in_front, z, torch.ones_like(z))  # keep culled rows finite
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    mean2d = torch.stack([fx * p[:, 0] / zs + cx, fy * p[:, 1] / zs + cy], dim=-1)  # [N, 2]

    # Jacobian at the mean with x/z, y/z clamped to the widened image
    x_over_z = p[:, 0] / zs
    y_over_z = p[:, 1] / zs
    x_over_z = x_over_z.clamp(-(cx + FRUSTUM_MARGIN * width) / fx, ((1 + FRUSTUM_MARGIN) * width - cx) / fx)
    y_over_z = y_over_z.clamp(-(cy + FRUSTUM_MARGIN * height) / fy, ((1 + FRUSTUM_MARGIN) * height - cy) / fy)
    zero = torch.zeros_like(zs)
    jac = torch.stack(
        [fx / zs, zero, -fx * x_over_z / zs, zero, fy / zs, -fy * y_over_z / zs], dim=-1
    ).reshape(n, 2, 3)
    rot = _rotation_matrix(rotations)
    sigma = rot @ torch.diag_embed(scales * scales) @ rot.mT  # [N, 3, 3]
    jw = jac @ rot_wc
    cov2d = jw @ sigma @ jw.mT + LOW_PASS * torch.eye(2, dtype=f64)  # [N, 2, 2]
    precision = torch.linalg.inv(cov2d)
    radius = EXTENT_SIGMAS * torch.sqrt(torch.linalg.eigvalsh(cov2d.detach())[:, -1])  # [N]

    ys, xs = torch.meshgrid(torch.arange(height, dtype=f64), torch.arange(width, dtype=f64), indexing="ij")
    centres = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1) + 0.5  # [HW, 2]
    d = centres[:, None, :] - mean2d[None, :, :]  # [HW, N, 2]
    maha = torch.einsum("pni,nij,pnj->pn", d, precision, d)
    alpha = torch.clamp(opacities[None, :] * torch.exp(-0.5 * maha), max=ALPHA_MAX)  # [HW, N]
    inside = (d.detach().abs() <= radius[None, :, None]).all(-1) & in_front[None, :]  # [HW, N]
    visible = inside.any(0)

    hw = width * height
    color = torch.zeros(hw, 3, dtype=f64)
    acc = torch.zeros(hw, dtype=f64)
    depth = torch.zeros(hw, dtype=f64)
    t = torch.ones(hw, dtype=f64)
    done = torch.zeros(hw, dtype=torch.bool)
    for i in sorted(range(n), key=lambda j: float(z[j].detach())):  # front to back (stable: ties in input order)
        a = alpha[:, i]
        skip = ~inside[:, i] | (a < ALPHA_MIN) | done
        t_next = t * (1 - a)
        stop = ~skip & (t_next < transmittance_min)
        done = done | stop
        draw = ~skip & ~stop
        w = torch.where(draw, a * t, torch.zeros_like(a))
        color = color + w[:, None] * colors[i]
        acc = acc + w
        depth = depth + w * z[i]
        t = torch.where(draw, t_next, t)
    if background is not None:
        color = color + t[:, None] * background.to(f64)
    return RasterOutput(
        color=color.t().reshape(3, height, width),
        alpha=acc.reshape(1, height, width),
        depth=depth.reshape(1, height, width),
        visible=visible,
    )
