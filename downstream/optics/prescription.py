"""Lens prescriptions for a near-eye magnifier: display (object) -> lens surfaces -> eye pupil.

A prescription is a small JSON-able dict (see :data:`CARDBOARD`); :class:`Prescription` checks it
and gives refractive indices. Lengths are millimetres, wavelengths nanometres. The optical axis is
+z from the display (z = 0) toward the eye; a surface's radius is positive when its centre of
curvature lies toward the eye.

Dispersion: a material is given as ``{"nd": n_d, "vd": V_d}`` and modelled with the two-term
Cauchy law ``n(lambda) = A + B / lambda^2`` fitted so that n(587.56 nm) = n_d and
n_F(486.13) - n_C(656.27) = (n_d - 1) / V_d. For PMMA (1.492, 57.4) this gives 1.49799 / 1.49383 /
1.48940 at 486 / 550 / 656 nm, within 2e-5 of a Buchdahl fit of the same (n_d, V_d).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any, Mapping

from controlgs_adapter.errors import InputValueError

__all__ = ["CARDBOARD", "Prescription", "cauchy_index"]

LAMBDA_D, LAMBDA_F, LAMBDA_C = 587.56, 486.13, 656.27  # nm

#: Google-Cardboard lens, paper Tbl. S1 (R1 faces the display).
CARDBOARD: dict[str, Any] = {
    "name": "google-cardboard",
    "display_mm": [24.0, 24.0],          # width, height of the display
    "object_distance_mm": 39.07,         # display -> first lens vertex
    "surfaces": [                        # in order from the display; "after" = medium behind the surface
        {"radius_mm": 290.444, "thickness_mm": 8.795, "after": {"nd": 1.492, "vd": 57.4, "name": "PMMA"},
         "semi_diameter_mm": 17.0},
        {"radius_mm": -25.498, "thickness_mm": 18.0, "after": "air", "semi_diameter_mm": 17.0},
    ],                                   # the last thickness is the eye relief (last vertex -> pupil)
    "pupil_diameter_mm": 4.0,
    "virtual_image_distance_mm": 667.0,  # accommodation distance, measured from the pupil
    "wavelengths_nm": [656.0, 550.0, 486.0],  # display primaries R, G, B (paper Eq. S1)
    "reference_wavelength_nm": 550.0,
}


def cauchy_index(nd: float, vd: float, wavelength_nm: float) -> float:
    """Refractive index from (n_d, V_d) with the two-term Cauchy law (see module docstring)."""
    inv2 = lambda lam: lam ** -2.0  # noqa: E731  1/nm^2: B's unit absorbs any scale of it, n is unitless
    b = (nd - 1.0) / vd / (inv2(LAMBDA_F) - inv2(LAMBDA_C))
    a = nd - b * inv2(LAMBDA_D)
    return a + b * inv2(wavelength_nm)


@dataclass(frozen=True)
class Surface:
    radius: float        # mm; math.inf for a plane
    thickness: float     # mm to the next surface (or to the pupil for the last one)
    material: Any        # "air" or {"nd", "vd"}
    semi_diameter: float


class Prescription:
    """A checked prescription. ``Prescription(CARDBOARD)`` or ``Prescription.cardboard()``."""

    def __init__(self, spec: Mapping[str, Any]):
        if not isinstance(spec, Mapping):
            raise InputValueError(f"prescription must be a mapping (JSON object) like CARDBOARD, got {type(spec).__name__}")
        self.spec = copy.deepcopy(dict(spec))
        s = self.spec
        for key in ("display_mm", "wavelengths_nm", "surfaces"):
            if key in s and not isinstance(s[key], (list, tuple)):
                raise InputValueError(f"prescription[{key!r}] must be a list, got {s[key]!r}")

        def pos(key: str, v: Any) -> float:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise InputValueError(f"prescription[{key!r}] must be a positive number, got {v!r}")
            return float(v)

        try:
            dw, dh = s["display_mm"]
            self.display_mm = (pos("display_mm", dw), pos("display_mm", dh))
            self.object_distance = pos("object_distance_mm", s["object_distance_mm"])
            self.pupil_radius = pos("pupil_diameter_mm", s["pupil_diameter_mm"]) / 2
            self.image_distance = pos("virtual_image_distance_mm", s["virtual_image_distance_mm"])
            self.wavelengths = tuple(pos("wavelengths_nm", w) for w in s["wavelengths_nm"])
            self.reference_wavelength = pos("reference_wavelength_nm", s.get("reference_wavelength_nm", 550.0))
            surfaces = s["surfaces"]
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, InputValueError):
                raise
            raise InputValueError(f"prescription is missing or has a malformed field: {e!r}; see CARDBOARD for the form") from e
        if not surfaces:
            raise InputValueError("prescription['surfaces'] must list at least one surface")
        self.surfaces: list[Surface] = []
        for i, sf in enumerate(surfaces):
            if not isinstance(sf, Mapping) or "thickness_mm" not in sf:
                raise InputValueError(f"surfaces[{i}] must be an object with 'thickness_mm' (see CARDBOARD), got {sf!r}")
            r = sf.get("radius_mm", math.inf)
            if r in (None, 0, "inf"):
                r = math.inf
            elif isinstance(r, bool) or not isinstance(r, (int, float)) or math.isnan(r):
                raise InputValueError(f"surfaces[{i}].radius_mm must be a number (or 0/null/'inf' for a plane), got {r!r}")
            r = float(r)
            mat = sf.get("after", "air")
            if mat != "air" and not (isinstance(mat, Mapping) and "nd" in mat and "vd" in mat):
                raise InputValueError(f"surfaces[{i}]['after'] must be 'air' or {{'nd': .., 'vd': ..}}, got {mat!r}")
            self.surfaces.append(Surface(r, pos(f"surfaces[{i}].thickness_mm", sf["thickness_mm"]), mat,
                                         pos(f"surfaces[{i}].semi_diameter_mm", sf.get("semi_diameter_mm", 1e9))))
        if self.surfaces[-1].material != "air":
            raise InputValueError("the medium behind the last surface (toward the eye) must be 'air'")

    @classmethod
    def cardboard(cls) -> "Prescription":
        return cls(CARDBOARD)

    def index(self, material: Any, wavelength_nm: float) -> float:
        return 1.0 if material == "air" else cauchy_index(material["nd"], material["vd"], wavelength_nm)

    @property
    def vertices(self) -> list[float]:
        """z of each surface vertex (display at z = 0)."""
        z, out = self.object_distance, []
        for sf in self.surfaces:
            out.append(z)
            z += sf.thickness
        return out

    @property
    def pupil_z(self) -> float:
        return self.vertices[-1] + self.surfaces[-1].thickness

    @property
    def image_z(self) -> float:
        """z of the virtual image plane (negative: behind the display)."""
        return self.pupil_z - self.image_distance
