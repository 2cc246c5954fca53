"""O_phys as a pipeline stage: linear RGB -> 3 display primaries -> shift-variant PSF -> linear RGB."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Literal, TypeGuard, get_args

import torch

from controlgs_adapter.checks import check_image
from controlgs_adapter.errors import InputValueError, warn_user
from controlgs_adapter.state import RuntimeState

from ..color import primaries_to_rgb, rgb_to_primaries
from ..placement import PLACEMENTS, Placement
from ..stage import Stage, StageContext
from .bank import PSFBank
from .operators import psf_distortion, psf_exact, psf_fast
from .resampled import RADIOMETRIES, Radiometry

if TYPE_CHECKING:
    from ..pipeline import Pipeline

__all__ = ["PSFOptics", "psf_optics", "set_optics_mode", "MODES", "DEFAULT_TOL", "DEFAULT_ZONE"]

Mode = Literal["distortion", "fast", "exact"]
MODES: tuple[Mode, ...] = get_args(Mode)
#: accuracy knob of the "fast" mode: relative residual of the truncated eigen-PSF expansion per
#: group of DEFAULT_ZONE x DEFAULT_ZONE field samples (docs/explanation/optics.md, "The operators")
DEFAULT_TOL = 0.02
DEFAULT_ZONE = 5


def psf_optics(image: torch.Tensor, bank: PSFBank | None = None, mode: Mode = "exact", tol: float = DEFAULT_TOL,
           zone: int = DEFAULT_ZONE, placement: Placement = "fit", radiometry: Radiometry = "radiance") -> torch.Tensor:
    """Functional O_phys. ``image [..., 3, H, W]`` linear RGB on the display -> linear RGB of the
    virtual image on the same grid (reference magnification). ``bank`` defaults to the shipped
    Cardboard bank; it is resampled once per (H, W, placement, device, dtype) and cached.
    ``placement``: where the image sits on the display (``"fit"``: square pixels, scaled to fit,
    centred; ``"stretch"``: the display stretched onto the image), see
    :mod:`controlgs_adapter.downstream.placement`. ``radiometry``: ``"radiance"`` (a lossless lens
    conserves radiance: a uniform display stays uniform up to the pupil transmission) or
    ``"energy"`` (the paper's Eq. S3: each display pixel's energy kept; a flat field falls as 1 / area
    magnification), docs/explanation/optics.md "Radiometry". A bank without PSFs (``bank.has_psf``
    False: made from a distortion profile, :mod:`.profiles`) gives distortion and lateral colour only:
    every mode runs the chief-ray warp (``"fast"`` and ``"exact"`` equal ``"distortion"``, at its cost)."""
    check_image("image", image)
    if not _is_mode(mode):
        raise InputValueError(f"mode must be one of {MODES}, got {mode!r}")
    bank = bank or PSFBank.default()
    if bank.num_wavelengths != 3:
        raise InputValueError(f"the optics stage needs a bank with 3 wavelengths (656/550/486 nm primaries), "
                              f"got {bank.wavelengths_nm}")
    H, W = image.shape[-2:]
    rb = bank.resample_to(H, W, device=image.device, dtype=image.dtype, placement=placement, radiometry=radiometry)
    prim = rgb_to_primaries(image)
    if mode == "distortion" or not bank.has_psf:
        out = psf_distortion(prim, rb)
    elif mode == "fast":
        out = psf_fast(prim, rb, tol, zone)
    else:
        out = psf_exact(prim, rb)
    return primaries_to_rgb(out)


class PSFOptics(Stage):
    """Shift-variant PSF optics (paper Eq. 5, S1-S4).

    Args:
        bank: a :class:`PSFBank`, a path to one, or None for the shipped Google-Cardboard bank.
        mode: ``"distortion"`` (chief-ray warp only; the paper's first 90 % of training), ``"fast"``
            (eigen-PSF shift-variant blur, see :func:`psf_fast`) or ``"exact"`` (paper Eq. S3 exactly, as
            per-field FFT convolutions; the default: on CPU it measured faster than ``"fast"`` at
            256-1024 px, docs/benchmarks/optics_bench.md). Settable at any time (``stage.mode = "distortion"``).
        tol, zone: accuracy knobs of ``"fast"`` (``tol=0`` is exact).
        placement: where the image sits on the display: ``"fit"`` (default; square pixels, scaled
            to fit and centred, the rest of the display black) or ``"stretch"`` (the display
            stretched onto the image, anisotropic pixels); :mod:`controlgs_adapter.downstream.placement`.
        radiometry: ``"radiance"`` (default; a lossless lens conserves radiance, so a uniform display
            is seen uniform up to the bank's pupil transmission) or ``"energy"`` (paper-faithful Eq. S3:
            each display pixel's energy kept, a flat field dims as 1 / area magnification: 0.80 at
            mid-edge and 0.60 in the corner of the Cardboard lens). All modes use the same one.
        stretch: deprecated; ``stretch=True`` is ``placement="stretch"``.
    """

    name = "optics"
    domain = "linear"
    order = 50.0

    def __init__(self, bank: PSFBank | str | os.PathLike | None = None, mode: Mode = "exact", tol: float = DEFAULT_TOL,
                 zone: int = DEFAULT_ZONE, placement: Placement = "fit", stretch: bool | None = None,
                 radiometry: Radiometry = "radiance") -> None:
        super().__init__()
        self.bank = PSFBank.load(bank) if isinstance(bank, (str, os.PathLike)) else (bank or PSFBank.default())
        if not (isinstance(tol, (int, float)) and 0 <= tol < 1):
            raise InputValueError(f"tol must be in [0, 1), got {tol!r}")
        if not isinstance(zone, int) or zone < 1:
            raise InputValueError(f"zone must be an int >= 1, got {zone!r}")
        if stretch is not None:
            warn_user('PSFOptics(stretch=...) is deprecated; use placement="stretch" or "fit"', DeprecationWarning)
            placement = "stretch" if stretch else "fit"
        if placement not in PLACEMENTS:
            raise InputValueError(f"placement must be one of {PLACEMENTS}, got {placement!r}")
        if radiometry not in RADIOMETRIES:
            raise InputValueError(f"radiometry must be one of {RADIOMETRIES}, got {radiometry!r}")
        self.tol, self.zone, self.placement, self.radiometry = float(tol), zone, placement, radiometry
        self.mode = mode

    @property
    def mode(self) -> Mode:
        return self._mode

    @mode.setter
    def mode(self, value: str) -> None:
        if not _is_mode(value):
            raise InputValueError(f"mode must be one of {MODES}, got {value!r}")
        self._mode = value

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:  # noqa: D102
        return psf_optics(image, self.bank, self.mode, self.tol, self.zone, self.placement, self.radiometry)

    def extra_repr(self) -> str:
        return (f"mode={self.mode!r}, placement={self.placement!r}, radiometry={self.radiometry!r}, tol={self.tol}, zone={self.zone}, "
                f"wavelengths={self.bank.wavelengths_nm}")


def set_optics_mode(pipeline: Pipeline, mode: str) -> None:
    """Set the mode (``"distortion"``, ``"fast"``, ``"exact"``) of ``pipeline``'s optics stage, if
    it has one; :class:`InputValueError` if that stage is not a :class:`PSFOptics` (it has no
    mode to set) or for another mode."""
    if "optics" not in pipeline:
        return
    optics = pipeline["optics"]
    if not isinstance(optics, PSFOptics):
        raise InputValueError(f"optics mode {mode!r}: the pipeline's optics stage must be a PSFOptics to take a mode, "
                              f"got {type(optics).__name__}")
    optics.mode = mode


def _is_mode(value: object) -> TypeGuard[Mode]:
    return value in MODES
