"""The pre-warp maps tied to a PSF bank (:mod:`.optics.bank`): :class:`BankMap` (the bank's chief
rays, grid ``[3, H, W, 2]`` evaluated at each image size), :class:`DisplayLUTMap` (a fitted table over
the whole display, one per optics mode) with its file format, the bank fingerprint that names the
bank a table was fitted for, and the look-ups of an optics stage's bank and placement.
"""

from __future__ import annotations

import hashlib
import math
import os
import weakref
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Mapping, TypeGuard

import torch
from torch import nn

from controlgs_adapter.checks import check_tensor
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError
from controlgs_adapter.formats.safetensors import load_tensors, save_tensors

from .lens_maps import PrewarpMap
from .placement import CARDBOARD_DISPLAY_MM, PLACEMENTS, Placement, image_region
from .warp import _FLOATS, _interp_regular, chief_ray_grid, pixel_grid

if TYPE_CHECKING:  # pragma: no cover
    from .optics.bank import PSFBank

__all__ = ["BankMap", "DisplayLUTMap", "bank_fingerprint", "DEFAULT_PREWARP_FILE"]

DISPLAY_LUT_KIND = "controlgs-prewarp-display-lut"
DISPLAY_LUT_FORMAT_VERSION = 1
_LUT_MODES = ("distortion", "exact", "fast")
#: the fitted pre-warp shipped for the shipped Cardboard bank (``controlgs optics fit-prewarp``)
DEFAULT_PREWARP_FILE = "cardboard_prewarp_lut.safetensors"


def _bank_in_image_frame(bank: "PSFBank", size: tuple[int, int],
                         placement: Placement) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A bank's chief rays in the normalised frame of an ``(H, W)`` image placed on its display:
    ``(chief [3, Cy, Cx, 2], sample_x [Cx], sample_y [Cy])``, display coordinates divided by the
    image region's half-extents (the frame the optics uses, ``ResampledBank``)."""
    region = image_region(int(size[0]), int(size[1]), bank.display_mm, placement)
    half = torch.tensor([region.half_x, region.half_y], dtype=bank.chief.dtype, device=bank.chief.device)
    return bank.chief / half, bank.chief_x / region.half_x, bank.chief_y / region.half_y


class BankMap(PrewarpMap):
    """The pre-warp that compensates a PSF bank's lens (distortion and lateral colour, one map per
    primary) for an image placed on the bank's display with ``placement``; the grid (and the
    ``"jacobian"`` gain, see :meth:`.lens.LensPrewarp.from_chief_ray_map`) is evaluated at each image
    size, so every aspect gets the region the optics simulates. Fixed (no parameters)."""

    def __init__(self, bank: "PSFBank", placement: Placement = "fit", gain: Literal["jacobian"] | None = None) -> None:
        super().__init__()
        if bank.chief.shape[0] != 3:
            raise InputValueError(f"bank must have 3 wavelengths (R, G, B primaries), got {bank.wavelengths_nm}")
        if placement not in PLACEMENTS:
            raise InputValueError(f"placement must be one of {PLACEMENTS}, got {placement!r}")
        if gain not in (None, "jacobian"):
            raise InputValueError(f"gain must be 'jacobian' or None, got {gain!r}")
        self.bank, self.placement, self.gain = bank, placement, gain
        ident = torch.stack(torch.meshgrid(bank.chief_x.float(), bank.chief_y.float(), indexing="xy"), -1)
        self._identity = gain is None and bool((bank.chief == ident).all())
        self._evaluated: tuple[tuple, tuple[torch.Tensor, torch.Tensor | None]] | None = None

    def is_identity(self) -> bool:  # noqa: D102
        return self._identity

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor | None]:  # noqa: D102
        key = (tuple(size), dtype, torch.device(device))
        if self._evaluated is None or self._evaluated[0] != key:
            chief, sx, sy = _bank_in_image_frame(self.bank, size, self.placement)
            grid, gain = chief_ray_grid(chief, size, sample_x=sx, sample_y=sy, gain=self.gain)
            self._evaluated = (key, (grid.to(device, dtype), None if gain is None else gain.to(device, dtype)))
        return self._evaluated[1]

    def extra_repr(self) -> str:
        return f"placement={self.placement!r}, gain={self.gain!r}"


def bank_fingerprint(bank: "PSFBank") -> str:
    """A short hash of a bank's optics (PSFs, pitches, chief rays, wavelengths, display size): a
    fitted LUT names the bank it was fitted for."""
    h = hashlib.sha256()
    for t in (bank.psf, bank.psf_pitch_mm, bank.field_x, bank.field_y, bank.chief, bank.chief_x, bank.chief_y):
        h.update(t.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
    h.update(repr((tuple(float(w) for w in bank.wavelengths_nm), tuple(float(d) for d in bank.display_mm))).encode())
    return h.hexdigest()[:16]


class DisplayLUTMap(PrewarpMap):
    """A fitted pre-warp tabulated in display coordinates over the whole display (one table per
    optics mode), sampled for the region an image occupies on the display (:mod:`.placement`), so
    one table serves images of any aspect.

    A table holds, at the pixel centres of an ``Hd x Wd`` grid over the display (display-normalised
    coordinates, ``align_corners=False``), per primary: ``displacement`` ``[3, Hd, Wd, 2]``, the
    display-normalised eye position of the display point minus the point (what the pre-warp samples
    there), and ``gain`` ``[3, Hd, Wd]``. For an ``H x W`` image with half-extents
    ``(hx, hy)`` the grid at image point ``u`` is ``(u h + displacement(u h)) / h`` (bilinear in the
    table, linear extrapolation at its border). The grid and gain are evaluated once per (size,
    dtype, device, table in use) and the same tensors returned again; an in-place change of a table
    is seen at the next call.

    The optics operators place light at the simulation's pixel pitch (box overlaps of footprints
    and PSF cells), which moves where a display pixel's light lands by up to ~0.1 px between
    pitches; a mode may therefore hold tables fitted at several display sizes (``sizes``). An image
    is then served by the two tables whose pixel pitch brackets its own (linear in the logarithm
    of the pitch; the nearest one beyond the fitted range).

    Args:
        tables: optics mode (``"distortion"``, ``"exact"``; ``"fast"`` uses ``"exact"``) ->
            ``(displacement, gain)``.
        display_mm: ``(width, height)`` of the display the tables cover.
        placement: where images sit on the display (``"fit"`` or ``"stretch"``).
        mode: the table to use; None: the mode of the optics stage given to :meth:`follow`, else
            the first table.
        meta: provenance (bank fingerprint, fit settings, residuals), saved with the tables.
        size: the display size (pixels along its shorter side) ``tables`` were fitted at; default
            the shorter side of ``meta["size"]`` when given, else None (one table serves every pitch).
        sizes: optics mode -> ``{display size: (displacement, gain)}``, tables of that mode fitted
            at further display sizes (needs ``size``).
    """

    def __init__(self, tables: Mapping[str, tuple[torch.Tensor, torch.Tensor]], display_mm: tuple[float, float] = CARDBOARD_DISPLAY_MM,
                 placement: Placement = "fit", mode: str | None = None, meta: Mapping[str, Any] | None = None,
                 *, size: int | None = None, sizes: Mapping[str, Mapping[int, tuple[torch.Tensor, torch.Tensor]]] | None = None,
                 ) -> None:
        super().__init__()
        if not tables:
            raise InputValueError("tables must hold at least one optics mode")
        if placement not in PLACEMENTS:
            raise InputValueError(f"placement must be one of {PLACEMENTS}, got {placement!r}")
        self.meta = dict(meta or {})
        if size is None and isinstance(self.meta.get("size"), (list, tuple)) and self.meta["size"]:
            size = min(int(v) for v in self.meta["size"])
        if size is not None and (isinstance(size, bool) or not isinstance(size, int) or size < 1):
            raise InputValueError(f"size must be an int >= 1 (display pixels along its shorter side), got {size!r}")
        sizes = dict(sizes or {})
        stray = sorted(set(sizes) - set(tables))
        if stray or (sizes and size is None):
            raise InputValueError(f"sizes needs the size of the main tables and a table of the same mode; got size={size!r}, "
                                  f"sizes for {sorted(sizes)}, tables for {sorted(tables)}")
        self.modes = tuple(tables)
        #: mode -> the display sizes of its tables, increasing (empty: the one table serves every pitch)
        self.sizes: dict[str, tuple[int, ...]] = {}
        for m, (disp, gain) in tables.items():
            if m not in _LUT_MODES:
                raise InputValueError(f"table modes must be among {_LUT_MODES}, got {m!r}")
            self._add_table(m, "", disp, gain)
            more = dict(sizes.get(m, {}))
            for n, (d, g) in more.items():
                if isinstance(n, bool) or not isinstance(n, int) or n < 1 or n == size:
                    raise InputValueError(f"sizes[{m!r}] keys must be ints >= 1 other than size={size}, got {n!r}")
                self._add_table(m, f"_{n}", d, g)
            self.sizes[m] = tuple(sorted([*more, size])) if size is not None else ()
        self.size = size
        self.display_mm = (float(display_mm[0]), float(display_mm[1]))
        self.placement = placement
        self.mode = mode
        self._optics: weakref.ref | None = None
        self._evaluated: tuple[tuple, tuple[torch.Tensor, torch.Tensor]] | None = None

    def _add_table(self, mode: str, suffix: str, disp: torch.Tensor, gain: torch.Tensor) -> None:
        b = check_tensor(f"displacement[{mode!r}]", disp, [3, "H", "W", 2], dtypes=_FLOATS, finite=True)
        check_tensor(f"gain[{mode!r}]", gain, [3, "H", "W"], dtypes=_FLOATS, dims=b, finite=True)
        if min(b["H"], b["W"]) < 2:
            raise ShapeError(f"table {mode!r} needs at least 2x2 samples, got {list(disp.shape)}")
        self.register_buffer(f"displacement_{mode}{suffix}", disp.detach().float())
        self.register_buffer(f"gain_{mode}{suffix}", gain.detach().float())

    def _tables_for(self, mode: str, pitch_mm: tuple[float, float]) -> list[tuple[str, float]]:
        """``[(buffer suffix, weight)]`` of the tables serving an image of pixel pitch ``pitch_mm``."""
        sizes = self.sizes.get(mode, ())
        if len(sizes) < 2:
            return [("", 1.0)]
        n = min(self.display_mm) / math.sqrt(pitch_mm[0] * pitch_mm[1])  # the image's pitch as a display size
        if n <= sizes[0] or n >= sizes[-1]:
            nearest = sizes[0] if n <= sizes[0] else sizes[-1]
            return [("" if nearest == self.size else f"_{nearest}", 1.0)]
        hi = next(k for k in sizes if k >= n)
        lo = sizes[sizes.index(hi) - 1]
        a = math.log(n / lo) / math.log(hi / lo)
        return [("" if k == self.size else f"_{k}", w) for k, w in ((lo, 1.0 - a), (hi, a)) if w > 0]

    def follow(self, optics: nn.Module) -> "DisplayLUTMap":
        """Use the table of ``optics.mode`` at every call (weakly referenced, not a submodule)."""
        self._optics = weakref.ref(optics)
        return self

    def table_mode(self) -> str:
        """The table in use (see the class docstring)."""
        optics = self._optics() if self._optics is not None else None
        want = self.mode if self.mode is not None else getattr(optics, "mode", None)
        if want is None:
            return self.modes[0]
        if want not in self.modes and want == "fast" and "exact" in self.modes:
            return "exact"
        if want not in self.modes:
            raise InputValueError(f"this pre-warp LUT has tables for {self.modes}, not for optics mode {want!r}")
        return want

    def is_identity(self) -> bool:  # noqa: D102
        return False

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: D102
        m = self.table_mode()
        region = image_region(int(size[0]), int(size[1]), self.display_mm, self.placement)
        used = [(getattr(self, f"displacement_{m}{sfx}"), getattr(self, f"gain_{m}{sfx}"), w)
                for sfx, w in self._tables_for(m, region.pitch_mm)]
        key = (tuple(size), dtype, torch.device(device), m,
               *((d.data_ptr(), d._version, g._version, w) for d, g, w in used))
        if self._evaluated is None or self._evaluated[0] != key:
            half = torch.tensor([region.half_x, region.half_y], dtype=dtype, device=device)
            p = pixel_grid(size, dtype, device) * half  # [H, W, 2] display-normalised
            val = sum(w * _interp_regular(torch.cat([d, g[..., None]], dim=-1).to(device=device, dtype=dtype),  # [3, Hd, Wd, 3]
                                          p.expand(3, -1, -1, -1)) for d, g, w in used)
            assert isinstance(val, torch.Tensor)
            self._evaluated = (key, ((p + val[..., :2]) / half, val[..., 2]))
        return self._evaluated[1]

    def save(self, path: str | os.PathLike) -> Path:
        """Write the tables (safetensors, atomic; kind ``controlgs-prewarp-display-lut``)."""
        tensors = {}
        for m in self.modes:
            for sfx in ["", *(f"_{n}" for n in self.sizes[m] if n != self.size)]:
                tensors[f"displacement_{m}{sfx}"] = getattr(self, f"displacement_{m}{sfx}")
                tensors[f"gain_{m}{sfx}"] = getattr(self, f"gain_{m}{sfx}")
        more = {m: [n for n in self.sizes[m] if n != self.size] for m in self.modes if len(self.sizes[m]) > 1}
        header = {"modes": list(self.modes), "display_mm": list(self.display_mm), "meta": self.meta,
                  **({"size": self.size, "sizes": more} if more else {}),
                  "units": {"displacement": "display-normalised (x, y) eye position minus display position",
                            "gain": "factor per primary (656, 550, 486 nm)"}}
        return save_tensors(path, tensors, header, kind=DISPLAY_LUT_KIND, format_version=DISPLAY_LUT_FORMAT_VERSION)

    @classmethod
    def load(cls, path: str | os.PathLike, placement: Placement = "fit") -> "DisplayLUTMap":
        """Read a file written by :meth:`save`."""
        tensors, header = load_tensors(path, kind=DISPLAY_LUT_KIND, max_version=DISPLAY_LUT_FORMAT_VERSION)
        modes = header.get("modes")
        if not isinstance(modes, list) or not modes:
            raise FileFormatError(f"{path}: display LUT header lacks its modes")
        more = header.get("sizes") or {}
        if not isinstance(more, dict) or not all(isinstance(v, list) and all(isinstance(n, int) and not isinstance(n, bool)
                                                                              for n in v) for v in more.values()):
            raise FileFormatError(f"{path}: display LUT header field 'sizes' must map modes to lists of display sizes, got {more!r}")
        suffixes = {m: ["", *(f"_{n}" for n in more.get(m, []))] for m in modes}
        missing = [k for m in modes for sfx in suffixes[m] for k in (f"displacement_{m}{sfx}", f"gain_{m}{sfx}")
                   if k not in tensors]
        if missing:
            raise FileFormatError(f"{path}: display LUT lacks {missing}")
        display_mm = header.get("display_mm", list(CARDBOARD_DISPLAY_MM))
        size = header.get("size")
        try:
            return cls({m: (tensors[f"displacement_{m}"], tensors[f"gain_{m}"]) for m in modes},
                       (float(display_mm[0]), float(display_mm[1])), placement, meta=header.get("meta") or {},
                       size=size if more else None,
                       sizes={m: {n: (tensors[f"displacement_{m}_{n}"], tensors[f"gain_{m}_{n}"]) for n in v}
                              for m, v in more.items()})
        except (InputValueError, ShapeError) as e:
            raise FileFormatError(f"{path}: {e}") from None

    def extra_repr(self) -> str:
        sized = {m: list(v) for m, v in self.sizes.items() if len(v) > 1}
        return f"modes={self.modes}, placement={self.placement!r}, display_mm={self.display_mm}" + (f", sizes={sized}" if sized else "")



def _optics_bank(optics: nn.Module) -> PSFBank:
    """The PSF bank (``optics.bank``) of an optics stage such as
    :class:`~.optics.stage.PSFOptics`; :class:`InputValueError` if it has none."""
    from .optics.bank import PSFBank

    bank = getattr(optics, "bank", None)
    if not isinstance(bank, PSFBank):
        raise InputValueError(f"optics must be an optics stage with a PSFBank as its bank, got a {type(optics).__name__} "
                              f"whose bank is a {type(bank).__name__}")
    return bank


def _is_placement(value: object) -> TypeGuard[Placement]:
    return value in PLACEMENTS


def _optics_placement(optics: nn.Module) -> Placement:
    """Where an optics stage places images on its display (``optics.placement``; ``"fit"`` if it
    has none); :class:`InputValueError` for another value."""
    placement = getattr(optics, "placement", "fit")
    if not _is_placement(placement):
        raise InputValueError(f"optics.placement must be one of {PLACEMENTS}, got {placement!r}")
    return placement
