"""The pre-warp maps that stand alone (:class:`PrewarpMap` and its analytic, tabulated and learned
kinds): each evaluates, at any image size ``(H, W)``, a sampling grid ``[3, H, W, 2]`` (normalised
(x, y), ``align_corners=False``) and a gain ``[3, H, W]`` (None: 1), for :class:`~.lens.LensPrewarp`.
"""

from __future__ import annotations

from typing import Sequence, cast

import torch
from torch import nn

from controlgs_adapter.checks import check_tensor
from controlgs_adapter.errors import InputValueError, ShapeError

from .placement import CARDBOARD_DISPLAY_MM, image_region
from .warp import _FLOATS, _interp_regular, pixel_grid

__all__ = ["CARDBOARD_RADIAL", "PrewarpMap", "RadialMap", "LUTMap", "MLPMap"]

#: Radial coefficients k1 per channel (R, G, B) fitted to the Cardboard lens's chief rays (the
#: display corner of a 1024 px, 24 mm display lands at 606.5 / 611.8 / 617.1 px from the centre
#: for 656 / 550 / 486 nm, docs/explanation/optics.md): ``1 + 2 k1 = landing / 512`` at the corner (r^2 = 2).
CARDBOARD_RADIAL: tuple[tuple[float], tuple[float], tuple[float]] = (
    (0.5 * (606.5 / 512.0 - 1.0),), (0.5 * (611.8 / 512.0 - 1.0),), (0.5 * (617.1 / 512.0 - 1.0),),
)


class PrewarpMap(nn.Module):
    """Source of the pre-warp: ``forward(size, dtype, device) -> (grid [3, H, W, 2], gain [3, H, W] | None)``."""

    def is_identity(self) -> bool:
        """True if the map is the identity (grid = pixel centres, gain = 1)."""
        raise NotImplementedError

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor | None]:  # noqa: D102
        raise NotImplementedError


class RadialMap(PrewarpMap):
    """``grid_c(p) = p * (1 + sum_k coefficients[c, k] r^(2k+2))`` (aspect-corrected r), gain 1.

    Args:
        coefficients: ``[3, K]`` radial coefficients per channel (R, G, B).
        learnable: make the coefficients a trainable parameter.
    """

    def __init__(self, coefficients: Sequence[Sequence[float]] | torch.Tensor = CARDBOARD_RADIAL, learnable: bool = False) -> None:
        super().__init__()
        k = torch.as_tensor(coefficients, dtype=torch.float64).float()  # checked as stored: 1e39 is inf in float32
        check_tensor("coefficients", k, [3, "K"], finite=True)
        if learnable:
            self.coefficients = nn.Parameter(k)
        else:
            self.register_buffer("coefficients", k)

        self._cache: dict[tuple, torch.Tensor] = {}  # fixed coefficients: grid per (size, dtype, device, version)

    def is_identity(self) -> bool:  # noqa: D102
        return not bool(self.coefficients.detach().any())

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, None]:  # noqa: D102
        if self.coefficients.requires_grad and torch.is_grad_enabled():
            return self._grid(size, dtype, device), None
        k = self.coefficients
        key = (tuple(size), dtype, torch.device(device), k.device, k.data_ptr(), k._version)
        if key not in self._cache:
            self._cache.clear()
            with torch.no_grad():
                self._cache[key] = self._grid(size, dtype, device)
        return self._cache[key], None

    def _grid(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> torch.Tensor:
        p = pixel_grid(size, dtype, device)  # [H, W, 2]
        region = image_region(int(size[0]), int(size[1]), CARDBOARD_DISPLAY_MM, "fit")
        aspect = torch.tensor([region.half_x, region.half_y], dtype=dtype, device=device)
        r2 = ((p * aspect) ** 2).sum(-1)  # [H, W] squared display-normalised radius
        k = self.coefficients.to(device=device, dtype=dtype)  # [3, K]
        powers = r2[None] ** torch.arange(1, k.shape[1] + 1, device=device, dtype=dtype)[:, None, None]  # [K, H, W]
        factor = 1.0 + torch.einsum("ck,khw->chw", k, powers)  # [3, H, W]
        return p[None] * factor[..., None]


class LUTMap(PrewarpMap):
    """A lookup table: grid ``[3, Hl, Wl, 2]`` and gain ``[3, Hl, Wl]`` (None: 1) at pixel centres
    of an ``Hl x Wl`` image; for another size the displacement and gain are interpolated bilinearly
    (linearly extrapolated at the border)."""

    displacement: torch.Tensor  # [3, Hl, Wl, 2] buffer: grid minus the pixel centres
    gain: torch.Tensor  # [3, Hl, Wl] buffer

    def __init__(self, grid: torch.Tensor, gain: torch.Tensor | None = None) -> None:
        super().__init__()
        b = check_tensor("grid", grid, [3, "H", "W", 2], dtypes=_FLOATS, finite=True)
        if min(b["H"], b["W"]) < 2:
            raise ShapeError(f"grid needs at least 2x2 pixels, got {list(grid.shape)}")
        if gain is None:
            gain = torch.ones(3, b["H"], b["W"], dtype=grid.dtype, device=grid.device)
        check_tensor("gain", gain, [3, "H", "W"], dtypes=_FLOATS, dims=b, finite=True)
        ident = pixel_grid((b["H"], b["W"]), grid.dtype, grid.device)
        self.register_buffer("displacement", (grid.detach() - ident).float())  # [3, Hl, Wl, 2]
        self.register_buffer("gain", gain.detach().float())  # [3, Hl, Wl]
        self._identity: tuple[tuple, bool] | None = None  # (buffer versions, answer)
        self._evaluated: tuple[tuple, tuple[torch.Tensor, torch.Tensor]] | None = None  # last (key, (grid, gain))

    def _version_key(self) -> tuple:
        return tuple((t.data_ptr(), t._version) for t in (self.displacement, self.gain))

    def is_identity(self) -> bool:  # noqa: D102
        key = self._version_key()
        if self._identity is None or self._identity[0] != key:  # O(N) scan only after a change
            self._identity = (key, not bool(self.displacement.any()) and bool((self.gain == 1).all()))
        return self._identity[1]

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: D102
        key = (tuple(size), dtype, torch.device(device), self._version_key())
        if self._evaluated is None or self._evaluated[0] != key:  # the table is fixed: evaluate once per size
            disp, gain = self.displacement.to(device=device, dtype=dtype), self.gain.to(device=device, dtype=dtype)
            p = pixel_grid(size, dtype, device)
            if tuple(size) != tuple(disp.shape[1:3]):
                table = torch.cat([disp, gain[..., None]], dim=-1)  # [3, Hl, Wl, 3]
                table = _interp_regular(table, p.expand(3, -1, -1, -1))
                disp, gain = table[..., :2], table[..., 2]
            self._evaluated = (key, (p[None] + disp, gain))
        return self._evaluated[1]



class MLPMap(PrewarpMap):
    """Learned map: an MLP from normalised (x, y) to 3 x (dx, dy, log gain), zero-initialised last
    layer (identity at init); :meth:`.lens.LensPrewarp.bake` tabulates it.

    Args:
        hidden: width of the hidden layers.
        layers: number of hidden layers.
        frequencies: number of Fourier-feature octaves of (x, y) fed to the MLP (0: raw x, y).
    """

    def __init__(self, hidden: int = 64, layers: int = 2, frequencies: int = 4) -> None:
        super().__init__()
        if hidden < 1 or layers < 1 or frequencies < 0:
            raise InputValueError(f"hidden, layers must be >= 1 and frequencies >= 0, got {hidden}, {layers}, {frequencies}")
        self.frequencies = int(frequencies)
        width_in = 2 + 4 * self.frequencies
        mods: list[nn.Module] = []
        for i in range(layers):
            mods += [nn.Linear(width_in if i == 0 else hidden, hidden), nn.SiLU()]
        last = nn.Linear(hidden, 9)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(*mods, last)

    def _last(self) -> nn.Linear:
        """The output layer (9 = 3 x (dx, dy, log gain))."""
        # nn.Sequential's stubs type its items as Module; __init__ ends it with this Linear
        return cast(nn.Linear, self.mlp[-1])

    def is_identity(self) -> bool:  # noqa: D102
        last = self._last()
        return not bool(last.weight.detach().any()) and not bool(last.bias.detach().any())

    def _encode(self, p: torch.Tensor) -> torch.Tensor:
        if self.frequencies == 0:
            return p
        scales = torch.pi * 2.0 ** torch.arange(self.frequencies, dtype=p.dtype, device=p.device)  # [F]
        angles = (p[..., None] * scales).flatten(-2)  # [..., 2F]
        return torch.cat([p, torch.sin(angles), torch.cos(angles)], dim=-1)

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: D102
        p = pixel_grid(size, dtype, device)  # [H, W, 2]
        mlp_dtype = self._last().weight.dtype
        out = self.mlp(self._encode(p.to(mlp_dtype))).to(dtype)  # [H, W, 9]
        out = out.reshape(*p.shape[:2], 3, 3).permute(2, 0, 1, 3)  # [3, H, W, (dx, dy, log gain)]
        return p[None] + out[..., :2], torch.exp(out[..., 2])
