"""Optics: PSF banks from lens prescriptions and shift-variant PSF operators (paper Eqs. 5, S1-S4).

- :class:`PSFBank` (``bank``): file format, the shipped Google-Cardboard bank, per-resolution resampling;
- :func:`build_bank` (``generate``): traces a bank from a prescription with the built-in ray tracer;
- ``operators``: :func:`psf_exact`, :func:`psf_fast`, :func:`psf_distortion`, :func:`psf_reference`;
- :class:`PSFOptics` / :func:`psf_optics` (``stage``): the pipeline stage ``"optics"``;
- :func:`load_lens`, :func:`effects_for_lens`, :data:`SHIPPED_LENSES` (``lenses``): choosing the lens.
"""

from .bank import PSFBank
from .generate import build_bank
from .lenses import SHIPPED_LENSES, Lens, effects_for_lens, load_lens
from .operators import psf_distortion, psf_exact, psf_fast, psf_reference
from .prescription import CARDBOARD, Prescription
from .stage import PSFOptics, psf_optics

__all__ = ["PSFBank", "build_bank", "psf_exact", "psf_fast", "psf_distortion", "psf_reference", "CARDBOARD",
           "Prescription", "PSFOptics", "psf_optics",
           "Lens", "load_lens", "effects_for_lens", "SHIPPED_LENSES"]
