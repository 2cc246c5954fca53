"""PSF banks: per field sample and wavelength, the chief-ray landing point and a local PSF.

Representation (justified with numbers in ``docs/explanation/optics.md``): every PSF is a ``K x K`` array
(K = 33 by default) whose sample pitch is chosen *per field and wavelength* so that all the light
fits: pitch = max(min_pitch, extent / 15.5). At the Cardboard centre the PSF is sub-pixel (EE80
0.6 px at 1024 px) and is stored at 1/8 px; in the corners it spans ~130 px and is stored at ~5 px.
A fixed pitch fine enough for the centre would need K ~ 1300 there. Samples are box cells: sample
``(i, j)`` holds the light in the cell centred at ``((j - K//2) * pitch, (i - K//2) * pitch)`` mm
from the chief ray (display-equivalent millimetres: virtual-image-plane distances divided by the
reference magnification), so resampling to any pixel pitch is an exact, energy-preserving
box-overlap (:meth:`PSFBank.resample_to`).

Coordinates: display-normalised ``[-1, 1]`` about the display centre (for an image that spans the
display, pixel centres at ``(2 i + 1) / W - 1``; an image of another aspect is placed by
:mod:`controlgs_adapter.downstream.placement`). Chief rays are given in the same normalised frame of the *output* (virtual
image) scaled by the reference magnification, so a distortion-free lens maps every point to itself.
PSF field samples lie at cell centres of a ``Gy x Gx`` grid (paper: 30 x 30); chief rays on their own
uniform ``Cy x Cx`` grid that includes the display edges (chief rays are cheap; the warp must hold
up to the corner).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from importlib import resources
from typing import TYPE_CHECKING, Any

import torch

from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.safetensors import load_tensors, save_tensors

from ..placement import Placement, image_region

if TYPE_CHECKING:
    from .resampled import Radiometry, ResampledBank

__all__ = ["PSFBank", "BANK_KIND", "BANK_FORMAT_VERSION", "DEFAULT_BANK_FILE"]

BANK_KIND = "psf_bank"
BANK_FORMAT_VERSION = 1
DEFAULT_BANK_FILE = "cardboard_psf_bank.safetensors"
SUM_TOLERANCE = 5e-3  # stored PSFs are float16: each must sum to 1 within this, then is renormalised


@dataclass
class PSFBank:
    """A field- and wavelength-dependent PSF bank.

    Attributes:
        psf: ``[L, Gy, Gx, K, K]`` unit-sum PSFs centred on the chief ray (sample ``K // 2``); row = y.
        psf_pitch_mm: ``[L, Gy, Gx]`` sample pitch of each PSF (display-equivalent mm).
        field_x, field_y: ``[Gx]``, ``[Gy]`` normalised display coordinates of the field samples.
        chief: ``[L, Cy, Cx, 2]`` chief-ray landing ``(x, y)``, normalised output coordinates.
        chief_x, chief_y: ``[Cx]``, ``[Cy]`` uniform normalised display coordinates, from -1 to 1.
        wavelengths_nm: one per channel, in the channel order of the primaries (656, 550, 486).
        display_mm: ``(width, height)`` of the display the bank was made for.
        meta: provenance (prescription, assumptions, measured figures, generator settings).
    """

    psf: torch.Tensor
    psf_pitch_mm: torch.Tensor
    field_x: torch.Tensor
    field_y: torch.Tensor
    chief: torch.Tensor
    chief_x: torch.Tensor
    chief_y: torch.Tensor
    wavelengths_nm: tuple[float, ...]
    display_mm: tuple[float, float]
    meta: dict[str, Any] = field(default_factory=dict)
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise :class:`InputValueError` naming what is wrong with the bank: every tensor is a real
        floating-point tensor of the documented shape holding finite values, ``wavelengths_nm`` and
        ``display_mm`` are finite positive numbers."""
        for name in ("psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x", "chief_y"):
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor) or not t.is_floating_point():
                what = t.dtype if isinstance(t, torch.Tensor) else type(t).__name__
                raise InputValueError(f"PSF bank: {name} must be a floating-point torch.Tensor, got {what}")
        self.wavelengths_nm = _positive_numbers("wavelengths_nm", self.wavelengths_nm, None)
        width_mm, height_mm = _positive_numbers("display_mm", self.display_mm, 2)
        self.display_mm = (width_mm, height_mm)
        psf, pitch, chief = self.psf, self.psf_pitch_mm, self.chief
        L = len(self.wavelengths_nm)
        if psf.dim() != 5 or psf.shape[-1] != psf.shape[-2] or psf.shape[-1] % 2 == 0:
            raise InputValueError(f"PSF bank: psf must be [L, Gy, Gx, K, K] with odd K, got {list(psf.shape)}")
        Gy, Gx = psf.shape[1:3]
        if min(psf.shape[:3]) < 1 or L < 1:
            raise InputValueError(f"PSF bank: empty grid: psf is {list(psf.shape)} with {L} wavelength(s); "
                                  "need >= 1 wavelength and >= 1 x 1 field samples")
        if psf.shape[0] != L:
            raise InputValueError(f"PSF bank: {psf.shape[0]} PSF channels but {L} wavelengths {self.wavelengths_nm}")
        if tuple(pitch.shape) != (L, Gy, Gx):
            raise InputValueError(f"PSF bank: psf_pitch_mm must be {[L, Gy, Gx]} to match psf, got {list(pitch.shape)}")
        if tuple(self.field_x.shape) != (Gx,) or tuple(self.field_y.shape) != (Gy,):
            raise InputValueError(f"PSF bank: field grid ({list(self.field_y.shape)}, {list(self.field_x.shape)}) "
                                  f"does not match the psf grid {Gy} x {Gx}")
        if chief.dim() != 4 or chief.shape[0] != L or chief.shape[-1] != 2:
            raise InputValueError(f"PSF bank: chief must be [L, Cy, Cx, 2] with L = {L}, got {list(chief.shape)}")
        if tuple(self.chief_x.shape) != (chief.shape[2],) or tuple(self.chief_y.shape) != (chief.shape[1],):
            raise InputValueError("PSF bank: chief grid coordinates do not match the chief tensor "
                                  f"({list(self.chief_y.shape)}, {list(self.chief_x.shape)} vs {list(chief.shape)})")
        for name, t in (("psf", psf), ("psf_pitch_mm", pitch), ("chief", chief), ("field_x", self.field_x),
                        ("field_y", self.field_y), ("chief_x", self.chief_x), ("chief_y", self.chief_y)):
            bad = (~torch.isfinite(t)).sum().item()
            if bad:
                raise InputValueError(f"PSF bank: {name} holds {bad} NaN/Inf values")
        if (pitch <= 0).any():
            raise InputValueError("PSF bank: psf_pitch_mm must be positive")
        if psf.min() < -1e-3:
            raise InputValueError(f"PSF bank: PSFs must be non-negative, min is {psf.min().item():.3g}")
        sums = psf.double().sum((-1, -2))
        worst = (sums - 1).abs().max().item()
        if worst > SUM_TOLERANCE:
            i = int((sums - 1).abs().argmax())
            raise InputValueError(f"PSF bank: every PSF must sum to 1 (+-{SUM_TOLERANCE}); PSF #{i} "
                                  f"(flat index over [L, Gy, Gx]) sums to {sums.flatten()[i].item():.6g}")
        for name, g in (("field_x", self.field_x), ("field_y", self.field_y)):
            if len(g) > 1 and not (g[1:] > g[:-1]).all() or g.abs().max() > 1:
                raise InputValueError(f"PSF bank: {name} must be increasing inside [-1, 1]")
        for name, g in (("chief_x", self.chief_x), ("chief_y", self.chief_y)):
            n = len(g)
            want = torch.linspace(-1, 1, n, dtype=torch.float64)
            if n < 2 or (g.double() - want).abs().max() > 1e-6:
                raise InputValueError(f"PSF bank: {name} must be uniform from -1 to 1 (linspace(-1, 1, {n}))")
        self.transmission                                     # noqa: B018  (raises on a malformed meta.transmission)
        self.psf = (psf.float() / sums.float()[..., None, None]).contiguous()
        self.psf_pitch_mm = pitch.float()
        self.chief = chief.float()

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike) -> None:
        """Write the bank (PSFs as float16, everything else float32) atomically."""
        tensors = {"psf": self.psf.half(), "psf_pitch_mm": self.psf_pitch_mm.float(), "field_x": self.field_x.float(),
                   "field_y": self.field_y.float(), "chief": self.chief.float(), "chief_x": self.chief_x.double(),
                   "chief_y": self.chief_y.double()}
        header = {"wavelengths_nm": list(self.wavelengths_nm), "display_mm": list(self.display_mm),
                  "units": {"chief": "normalised output coordinates [-1, 1] (x right, y down)",
                            "field_x/field_y/chief_x/chief_y": "normalised display coordinates [-1, 1]",
                            "psf_pitch_mm": "display-equivalent millimetres (virtual image / reference magnification)",
                            "psf": "unit-sum box-cell energies, sample K//2 on the chief ray, row = y"},
                  "shapes": {k: list(v.shape) for k, v in tensors.items()}, "meta": self.meta}
        save_tensors(path, tensors, header, kind=BANK_KIND, format_version=BANK_FORMAT_VERSION)

    @classmethod
    def load(cls, path: str | os.PathLike, *, display_mm: tuple[float, float] | None = None) -> "PSFBank":
        """Load a bank; with ``display_mm`` given, refuse a bank made for another display size."""
        t, h = load_tensors(path, kind=BANK_KIND, max_version=BANK_FORMAT_VERSION)
        missing = {"psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x", "chief_y"} - set(t)
        if missing:
            raise FileFormatError(f"{path}: PSF bank lacks tensors {sorted(missing)}")
        wavelengths = _header_numbers(path, h, "wavelengths_nm", None)
        display_w, display_h = _header_numbers(path, h, "display_mm", 2)
        meta = h.get("meta", {})
        if not isinstance(meta, dict):
            raise FileFormatError(f"{path}: header field 'meta' must be a JSON object, got {type(meta).__name__}")
        try:
            bank = cls(psf=t["psf"].float(), psf_pitch_mm=t["psf_pitch_mm"], field_x=t["field_x"], field_y=t["field_y"],
                       chief=t["chief"], chief_x=t["chief_x"], chief_y=t["chief_y"],
                       wavelengths_nm=wavelengths, display_mm=(display_w, display_h), meta=meta)
        except InputValueError as e:
            raise FileFormatError(f"{path}: {e}") from e
        if display_mm is not None and any(abs(a - b) > 1e-6 * max(a, b) for a, b in zip(bank.display_mm, display_mm)):
            raise FileFormatError(f"{path}: bank was made for a {bank.display_mm[0]} x {bank.display_mm[1]} mm display, "
                                  f"expected {display_mm[0]} x {display_mm[1]} mm")
        return bank

    @classmethod
    def default(cls) -> "PSFBank":
        """The shipped Google-Cardboard bank (30 x 30 fields, 656/550/486 nm); loaded once per process."""
        global _DEFAULT
        if _DEFAULT is None:
            path = resources.files("controlgs_adapter.data").joinpath(DEFAULT_BANK_FILE)
            with resources.as_file(path) as p:
                _DEFAULT = cls.load(p)
        return _DEFAULT

    # ------------------------------------------------------------------ the lens it describes
    @property
    def lens(self) -> dict[str, Any]:
        """``meta["lens"]``, the lens's frame: ``{"axis": [ax, ay], "rotationally_symmetric": bool,
        "psf": bool, "kind": str}``; a bank without one (the shipped Cardboard bank) is a centred,
        rotationally symmetric lens traced from a prescription."""
        lens = self.meta.get("lens")
        if lens is None:
            return {"axis": [0.0, 0.0], "rotationally_symmetric": True, "psf": True, "kind": "prescription"}
        if not isinstance(lens, dict):
            raise InputValueError(f"PSF bank: meta.lens must be an object, got {type(lens).__name__}")
        return lens

    @property
    def axis(self) -> tuple[float, float]:
        """Where the lens's optical axis meets the display, in normalised display coordinates
        (``display_offset_mm`` divided by the display's half-extents; ``(0, 0)``: centred)."""
        a = self.lens.get("axis", [0.0, 0.0])
        if (not isinstance(a, (list, tuple)) or len(a) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in a)):
            raise InputValueError(f"PSF bank: meta.lens.axis must be two finite numbers, got {a!r}")
        return float(a[0]), float(a[1])

    @property
    def rotationally_symmetric(self) -> bool:
        """True if the lens is rotationally symmetric about an axis through the display centre
        (no decentre, tilt or display offset): the lens condition is then the anchor's radius."""
        return bool(self.lens.get("rotationally_symmetric", True)) and self.axis == (0.0, 0.0)

    @property
    def has_psf(self) -> bool:
        """False for a bank made from a distortion profile: chief rays only, every PSF a unit impulse."""
        return bool(self.lens.get("psf", True))

    # ------------------------------------------------------------------ resampling
    @property
    def num_wavelengths(self) -> int:
        return len(self.wavelengths_nm)

    @property
    def transmission(self) -> torch.Tensor:
        """``[L, Gy, Gx]`` float64 traced pupil transmission per field sample (fraction of the eye pupil's
        area whose rays pass every lens aperture: ``meta["transmission"]``; ones if the bank has none)."""
        shape = tuple(self.psf.shape[:3])
        t = self.meta.get("transmission")
        if t is None:
            return torch.ones(shape, dtype=torch.float64)
        try:
            t = torch.as_tensor(t, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError) as e:
            raise InputValueError(f"PSF bank: meta.transmission must be numbers of shape {list(shape)}") from e
        if tuple(t.shape) != shape or not torch.isfinite(t).all() or t.min() < 0 or t.max() > 1:
            raise InputValueError(f"PSF bank: meta.transmission must be {list(shape)} numbers in [0, 1], "
                                  f"got shape {list(t.shape)}")
        return t

    def resample_to(self, height: int, width: int, *, device: torch.device | str = "cpu",
                    dtype: torch.dtype = torch.float32, placement: Placement = "fit",
                    radiometry: "Radiometry" = "radiance") -> "ResampledBank":
        """The bank at a simulation resolution (cached per size/placement/radiometry/device/dtype;
        no ray tracing).

        ``placement`` says where the ``height x width`` image sits on the display
        (:mod:`controlgs_adapter.downstream.placement`): ``"fit"`` (square pixels, scaled to fit,
        centred; only the image's region is simulated, the rest of the display is black) or
        ``"stretch"`` (the display stretched onto the image, anisotropic pixels).
        ``radiometry``: ``"radiance"`` (default: a lossless lens conserves radiance, a uniform display
        stays uniform up to the pupil transmission) or ``"energy"`` (paper Eq. S3: each display
        pixel's energy kept, a flat field falls as 1 / area magnification); :mod:`.resampled`.
        """
        if not (isinstance(height, int) and isinstance(width, int)) or height < 2 or width < 2:
            raise InputValueError(f"resample_to: height and width must be ints >= 2, got {height!r}, {width!r}")
        from .resampled import RADIOMETRIES, ResampledBank

        if radiometry not in RADIOMETRIES:
            raise InputValueError(f"radiometry must be one of {RADIOMETRIES}, got {radiometry!r}")
        region = image_region(height, width, self.display_mm, placement)
        try:  # the device as tensors report it: "cuda" -> cuda:0, "cpu:0" -> cpu
            device = torch.empty(0, device=device).device
        except (RuntimeError, TypeError, AssertionError) as e:  # unknown name, not a device, not built in
            raise InputValueError(f"resample_to: device {device!r} is not a usable torch device here ({e})") from None
        key = (height, width, placement, radiometry, str(device), dtype)
        if key not in self._cache:
            self._cache[key] = ResampledBank(self, height, width, region, device=device, dtype=dtype,
                                             radiometry=radiometry)
        return self._cache[key]


_DEFAULT: PSFBank | None = None


def _positive_numbers(name: str, value: Any, count: int | None) -> tuple[float, ...]:
    """``value`` as a tuple of finite positive floats (``count`` of them if given; an empty tuple is
    left to the grid check), else :class:`InputValueError` naming the argument (a string or a bool
    is not a number)."""
    want = f"{count} finite positive numbers" if count else "finite positive numbers"
    if isinstance(value, (str, bytes, torch.Tensor)) or not hasattr(value, "__len__") or not hasattr(value, "__iter__"):
        raise InputValueError(f"PSF bank: {name} must be a sequence of {want}, got {value!r}")
    items = list(value)
    ok = (count is None or len(items) == count) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in items)
    if not ok:
        raise InputValueError(f"PSF bank: {name} must be {want}, got {value!r}")
    return tuple(float(v) for v in items)


def _header_numbers(path: str | os.PathLike, header: dict[str, Any], key: str, count: int | None) -> tuple[float, ...]:
    """Header field ``key`` as a tuple of finite positive numbers (``count`` of them if given):
    :class:`FileFormatError` naming the file and the field otherwise (a string such as ``"66"``
    is refused, not read digit by digit)."""
    value = header.get(key)
    want = f"a list of {count if count else 'one or more'} positive numbers"
    if not isinstance(value, list) or (count is not None and len(value) != count) or not value:
        raise FileFormatError(f"{path}: header field {key!r} must be {want}, got {value!r}")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in value):
        raise FileFormatError(f"{path}: header field {key!r} must be {want}, got {value!r}")
    return tuple(float(v) for v in value)
