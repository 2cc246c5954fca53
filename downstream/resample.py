"""Anti-aliasing resampling P_res (paper Eq. 3, Supp. "Anti-Aliasing Resampling").

The image is supersampled at the native resolution S and box-filtered ("area" filter) to the
display sampling rate S/d for a continuous factor d >= 1. Each output pixel is the exact area
average of the input pixels it covers: along an axis of ``S`` pixels resampled to
``n = max(1, round(S / d))`` pixels (the same rounding as :meth:`Camera.scaled`), output pixel
``j`` covers ``[j S/n, (j+1) S/n)`` and input pixel ``i`` contributes its overlap with that
interval divided by ``S/n``. For an integer ``d`` that divides S this is exactly average pooling
(and uses ``avg_pool2d``). The filter is separable and applied as two banded row gathers
(``ceil(S/n) + 1`` taps per output pixel), so its cost is O(S^2) whatever d is.

Domain: linear light (filtering averages emitted light; decode sRGB before, as the pipeline does).

The no-supersampling baseline of the paper (the backbone rendered directly at S/d) is not a
filter: render at ``camera.scaled(d)`` and pass that image to the pipeline with the ground truth
at S as ``reference`` (or ``native_size=S``); this stage then sees an image already at the display
size and passes it through untouched.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F

from controlgs_adapter.checks import check_image
from controlgs_adapter.errors import ShapeError, StateRangeError
from controlgs_adapter.state import RuntimeState

from .stage import Stage, StageContext

__all__ = ["area_resample", "resampled_size", "AreaResample"]


def _check_factor(d: object, name: str = "d") -> float:
    try:
        value = float(d)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise StateRangeError(f"{name} must be a real number >= 1 (S / display rate), got {d!r}") from None
    if not math.isfinite(value) or value < 1.0:
        raise StateRangeError(f"{name} must be a finite number >= 1 (S / display rate), got {d!r}")
    return value


def resampled_size(size: tuple[int, int], d: float) -> tuple[int, int]:
    """``(H, W)`` -> ``(max(1, round(H/d)), max(1, round(W/d)))``, the display size at factor d."""
    d = _check_factor(d)
    return max(1, round(size[0] / d)), max(1, round(size[1] / d))


@lru_cache(maxsize=64)
def _area_taps(n_in: int, n_out: int, dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices ``[n_out, K]`` (long) and weights ``[n_out, K]`` of the 1-D area filter n_in -> n_out."""
    j = torch.arange(n_out, dtype=torch.float64)
    lo = j * n_in / n_out  # [n_out] interval starts (exact for integer ratios)
    hi = (j + 1) * n_in / n_out
    first = torch.floor(lo).long()
    taps = int(math.ceil(n_in / n_out)) + 1
    idx = first[:, None] + torch.arange(taps)[None, :]  # [n_out, K]
    left = torch.maximum(idx.double(), lo[:, None])
    right = torch.minimum(idx.double() + 1.0, hi[:, None])
    w = (right - left).clamp(min=0.0) * (n_out / n_in)  # taps past the end overlap nothing: hi <= n_in exactly
    w = w / w.sum(dim=1, keepdim=True)  # exact partition of unity despite float rounding
    return idx.clamp(max=n_in - 1).to(device), w.to(dtype=dtype, device=device)


def _resample_rows(x: torch.Tensor, n_out: int) -> torch.Tensor:
    """Area filter along dim -2 (whole rows are gathered: contiguous copies), ``K`` taps."""
    n_in = x.shape[-2]
    if n_in == n_out:
        return x
    idx, w = _area_taps(n_in, n_out, x.dtype, x.device)
    out = x.index_select(-2, idx[:, 0]) * w[:, 0, None]
    for k in range(1, idx.shape[1]):
        out = out + x.index_select(-2, idx[:, k]) * w[:, k, None]
    return out


def _area_resample_to(image: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    h, w = image.shape[-2:]
    if (h, w) == tuple(size):
        return image
    k = h // size[0]
    if k * size[0] == h and k * size[1] == w:  # an integer factor, the same on both axes
        flat = image.reshape(-1, 3, h, w)
        return F.avg_pool2d(flat, k).reshape(*image.shape[:-2], *size)
    rows = _resample_rows(image, size[0])  # [..., h', W]
    return _resample_rows(rows.transpose(-1, -2), size[1]).transpose(-1, -2).contiguous()


def area_resample(image: torch.Tensor, d: float) -> torch.Tensor:
    """Box-filter ``image`` from S to S/d (exact area weights).

    Args:
        image: ``[..., 3, H, W]`` float32/float64, linear light.
        d: downsampling factor, finite, >= 1 (continuous).
    Returns:
        ``[..., 3, round(H/d), round(W/d)]`` (each at least 1); ``image`` itself when d == 1.
        At an integer factor k that divides both H and W (a non-square frame included) each output
        pixel is its k x k block's sum divided by k * k (one average pool): the correctly rounded mean
        when the block sum is exact (e.g. 8-bit pixel values).
    """
    check_image("image", image, finite=False)
    return _area_resample_to(image, resampled_size((image.shape[-2], image.shape[-1]), d))


class AreaResample(Stage):
    """P_res: area filter from the native resolution S to S/d (``state.downsample``).

    Args:
        max_factor: largest d this scene/run supports (the paper trains d in [1, 8]); a larger
            state raises :class:`StateRangeError`.
    """

    name = "resample"
    domain = "linear"
    order = 20.0

    def __init__(self, max_factor: float = 8.0) -> None:
        super().__init__()
        self.max_factor = _check_factor(max_factor, "max_factor")

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:  # noqa: D102
        return state.downsample == 1.0

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        """``[..., 3, S_h, S_w]`` -> ``[..., 3, round(S_h/d), round(S_w/d)]``; an image already at
        the display size (no-SS baseline) passes through."""
        d = state.downsample
        if d > self.max_factor:
            raise StateRangeError(f"downsample {d} exceeds this pipeline's max_factor {self.max_factor}")
        size = tuple(image.shape[-2:])
        target = resampled_size(ctx.native_size, d)
        if size == target:
            return image
        if size != tuple(ctx.native_size):
            raise ShapeError(
                f"image must be at the native size {tuple(ctx.native_size)} or the display size {target} "
                f"for downsample {d}, got {size}"
            )
        return area_resample(image, d)
