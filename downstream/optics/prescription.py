"""Lens prescriptions for a near-eye magnifier: display (object) -> lens surfaces -> eye pupil.

A prescription is a small JSON-able dict (see :data:`CARDBOARD`); :class:`Prescription` checks it
and gives refractive indices. Lengths are millimetres, wavelengths nanometres. The optical axis is
+z from the display (z = 0) toward the eye; a surface's radius is positive when its centre of
curvature lies toward the eye (+z), whichever way the light travels.

Optional per surface:

- ``conic`` (k) and ``aspheric`` ([A4, A6, ...]): the even asphere
  ``z = c r^2 / (1 + sqrt(1 - (1 + k) c^2 r^2)) + sum_i A_2i r^2i`` (c = 1 / radius_mm, r in mm);
  k = 0 sphere, -1 paraboloid, (-1, 0) prolate ellipsoid, < -1 hyperboloid;
- ``decenter_mm`` [x, y] and ``tilt_deg`` [a, b]: the surface alone is moved (the surfaces after it
  stay on the axis): its vertex to ``(x, y, z_vertex)``, then rotated about that vertex by ``a``
  about the x axis, then by ``b`` about the (fixed) y axis: ``p_global = vertex + R_y(b) R_x(a) p_local``
  (right-handed, a positive ``a`` turns +y toward +z);
- ``"after": "mirror"``: the surface reflects; the medium after it is the medium before it and the
  light travels back, so the thicknesses after an odd number of mirrors are negative (a sequential
  folded path, e.g. a pancake lens unrolled into its double pass). After the last surface the light
  must travel toward the eye (+z): an even number of mirrors.

Optional per system: ``display_offset_mm`` [x, y], the display point the lens axis meets,
measured from the display centre (the eye pupil stays on the lens axis), and ``efficiency`` in
(0, 1], the throughput of the modelled path (e.g. 0.25 for a pancake's two half-mirror passes).

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

__all__ = ["CARDBOARD", "Prescription", "Surface", "cauchy_index"]

_SYSTEM_KEYS = {"name", "display_mm", "object_distance_mm", "surfaces", "pupil_diameter_mm",
                "virtual_image_distance_mm", "wavelengths_nm", "reference_wavelength_nm", "display_offset_mm",
                "efficiency", "source", "licence", "notes"}
_SURFACE_KEYS = {"radius_mm", "thickness_mm", "after", "semi_diameter_mm", "conic", "aspheric", "decenter_mm",
                 "tilt_deg", "name"}

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
    thickness: float     # mm to the next surface (or to the pupil for the last one); < 0 travelling back
    material: Any        # "air" or {"nd", "vd"}: the medium after the surface (a mirror's: the one before it)
    semi_diameter: float
    conic: float = 0.0
    aspheric: tuple[float, ...] = ()           # A4, A6, ... (mm^-3, mm^-5, ...)
    decenter: tuple[float, float] = (0.0, 0.0)  # mm
    tilt: tuple[float, float] = (0.0, 0.0)      # degrees, about x then y
    mirror: bool = False

    @property
    def curvature(self) -> float:
        """Vertex curvature c = 1 / radius (1/mm; 0 for a plane)."""
        return 0.0 if math.isinf(self.radius) else 1.0 / self.radius

    @property
    def moved(self) -> bool:
        """Decentred or tilted."""
        return self.decenter != (0.0, 0.0) or self.tilt != (0.0, 0.0)


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
        self.display_offset = self._pair(s, "display_offset_mm", "prescription['display_offset_mm']")
        eff = s.get("efficiency", 1.0)
        if isinstance(eff, bool) or not isinstance(eff, (int, float)) or not (0 < eff <= 1):
            raise InputValueError(f"prescription['efficiency'] must be a number in (0, 1], got {eff!r}")
        self.efficiency = float(eff)
        unknown = sorted(set(s) - _SYSTEM_KEYS)
        if unknown:
            raise InputValueError(f"prescription has unknown keys {unknown}; known: {sorted(_SYSTEM_KEYS)}")
        self.surfaces: list[Surface] = []
        n_mirrors, material = 0, "air"
        for i, sf in enumerate(surfaces):
            self.surfaces.append(self._surface(i, sf, material, n_mirrors % 2 == 1))
            material = self.surfaces[-1].material
            n_mirrors += self.surfaces[-1].mirror
        if n_mirrors % 2:
            raise InputValueError(f"prescription has {n_mirrors} mirrors: after the last surface the light must "
                                  "travel toward the eye (+z), which needs an even number of mirrors")
        if self.surfaces[-1].material != "air":
            raise InputValueError("the medium behind the last surface (toward the eye) must be 'air'")

    @staticmethod
    def _pair(obj: Mapping[str, Any], key: str, name: str) -> tuple[float, float]:
        """An optional ``[x, y]`` of finite numbers (default ``(0, 0)``)."""
        v = obj.get(key, (0.0, 0.0))
        if not isinstance(v, (list, tuple)) or len(v) != 2 or not all(
                not isinstance(a, bool) and isinstance(a, (int, float)) and math.isfinite(a) for a in v):
            raise InputValueError(f"{name} must be [x, y], two finite numbers, got {v!r}")
        return float(v[0]) + 0.0, float(v[1]) + 0.0   # -0.0 -> 0.0

    def _surface(self, i: int, sf: Any, before: Any, backward: bool) -> Surface:
        """Check ``surfaces[i]``; ``before`` is the medium in front of it, ``backward`` whether the light
        reaching it travels toward the display (after an odd number of mirrors)."""
        name = f"surfaces[{i}]"
        if not isinstance(sf, Mapping) or "thickness_mm" not in sf:
            raise InputValueError(f"{name} must be an object with 'thickness_mm' (see CARDBOARD), got {sf!r}")
        unknown = sorted(set(sf) - _SURFACE_KEYS)
        if unknown:
            raise InputValueError(f"{name} has unknown keys {unknown}; known: {sorted(_SURFACE_KEYS)}")
        r = sf.get("radius_mm", math.inf)
        if r in (None, 0, "inf"):
            r = math.inf
        elif isinstance(r, bool) or not isinstance(r, (int, float)) or math.isnan(r):
            raise InputValueError(f"{name}.radius_mm must be a number (or 0/null/'inf' for a plane), got {r!r}")
        r = float(r)
        mat = sf.get("after", "air")
        mirror = mat == "mirror"
        if mirror:
            mat = before
        elif mat != "air" and not (isinstance(mat, Mapping) and "nd" in mat and "vd" in mat):
            raise InputValueError(f"{name}['after'] must be 'air', 'mirror' or {{'nd': .., 'vd': ..}}, got {mat!r}")
        t = sf["thickness_mm"]
        backward ^= mirror
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t == 0 or (t < 0) != backward:
            want = "negative (the light travels back after an odd number of mirrors)" if backward else "positive"
            raise InputValueError(f"prescription[{name + '.thickness_mm'!r}] must be a {want} number, got {t!r}")
        semi = sf.get("semi_diameter_mm", 1e9)
        if isinstance(semi, bool) or not isinstance(semi, (int, float)) or not math.isfinite(semi) or semi <= 0:
            raise InputValueError(f"prescription[{name + '.semi_diameter_mm'!r}] must be a positive number, got {semi!r}")
        k = sf.get("conic", 0.0)
        if isinstance(k, bool) or not isinstance(k, (int, float)) or not math.isfinite(k):
            raise InputValueError(f"{name}.conic must be a finite number, got {k!r}")
        asph = sf.get("aspheric", [])
        if not isinstance(asph, (list, tuple)) or not all(
                not isinstance(a, bool) and isinstance(a, (int, float)) and math.isfinite(a) for a in asph):
            raise InputValueError(f"{name}.aspheric must be a list of finite numbers [A4, A6, ...], got {asph!r}")
        c = 0.0 if math.isinf(r) else 1.0 / r
        if "semi_diameter_mm" in sf and 1.0 - (1.0 + k) * c * c * semi * semi < 0:
            raise InputValueError(f"{name}: the conic (radius_mm {r:g}, conic {k:g}) has no sag at its semi_diameter_mm "
                                  f"{semi:g} (1 - (1 + k) c^2 r^2 < 0); reduce semi_diameter_mm")
        return Surface(r, float(t), mat, float(semi), float(k) + 0.0, tuple(float(a) for a in asph),
                       self._pair(sf, "decenter_mm", f"{name}.decenter_mm"),
                       self._pair(sf, "tilt_deg", f"{name}.tilt_deg"), mirror)

    @classmethod
    def cardboard(cls) -> "Prescription":
        return cls(CARDBOARD)

    def index(self, material: Any, wavelength_nm: float) -> float:
        return 1.0 if material == "air" else cauchy_index(material["nd"], material["vd"], wavelength_nm)

    @property
    def rotationally_symmetric(self) -> bool:
        """No surface decentred or tilted and the display centred on the lens axis."""
        return self.display_offset == (0.0, 0.0) and not any(sf.moved for sf in self.surfaces)

    @property
    def path_length(self) -> float:
        """Display -> pupil along the (unfolded) axis, mm: ``pupil_z`` when there are no mirrors."""
        z = self.object_distance
        for sf in self.surfaces:
            z += abs(sf.thickness)
        return z

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
