"""The shipped lenses side by side: a table of their figures (markdown, printed) and a picture of their PSFs.

Figures per lens, from its prescription (the library's ray tracer) and its shipped PSF bank: focal length
at 550 nm; full field of view across the display's width and diagonal; distortion of the chief ray at
the display's mid-edge and corner (against the on-axis magnification); lateral colour, the 486 - 656 nm
chief-ray separation in the eye (arcmin); the RMS radius of the bank's 550 nm PSF (geometric spot with
the pupil's diffraction) at the field samples nearest the centre, the mid-edge and the corner (arcmin);
the size of a display pixel at 1024 px across (arcmin) and the path efficiency. The picture shows each
lens's PSFs (656 / 550 / 486 nm as R / G / B, square-root scale) at the same field samples, in arcmin.

    python scripts/compare_lenses.py [--png docs/explanation/lens-psfs.png]   # needs the demo extra
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.lenses import SHIPPED_LENSES, load_lens, shipped_prescription
from controlgs_adapter.downstream.optics.prescription import Prescription
from controlgs_adapter.downstream.optics.raytrace import chief_ray, paraxial, real_magnification

ARCMIN = 180 / math.pi * 60
#: field samples shown (normalised display coordinates; the bank's nearest sample is used)
FIELDS = {"centre": (0.0, 0.0), "mid-edge": (1.0, 0.0), "corner": (1.0, 1.0)}


def _angle(rx: Prescription, lam: float, h: float) -> float:
    """Chief-ray angle (rad) in the eye of display height ``h`` mm (the lens is rotationally symmetric)."""
    _, Y, ok = chief_ray(rx, lam, np.array([h]))
    assert ok[0], f"chief ray at {h} mm blocked"
    return math.atan2(float(Y[0]), rx.image_distance)


def _nearest(bank: PSFBank, u: float, v: float) -> tuple[int, int]:
    return int((bank.field_y - v).abs().argmin()), int((bank.field_x - u).abs().argmin())


def psf_rms_arcmin(bank: PSFBank, rx: Prescription, li: int, iy: int, ix: int) -> float:
    """RMS radius about its centroid of the bank's PSF of primary ``li`` at field sample ``(iy, ix)``, in the eye."""
    p = bank.psf[li, iy, ix].double().numpy()
    k = p.shape[-1]
    t = (np.arange(k) - k // 2) * float(bank.psf_pitch_mm[li, iy, ix])
    ty, tx = np.meshgrid(t, t, indexing="ij")
    cx, cy = (p * tx).sum(), (p * ty).sum()
    rms_mm = math.sqrt(float((p * ((tx - cx) ** 2 + (ty - cy) ** 2)).sum()))
    return rms_mm * real_magnification(rx, rx.reference_wavelength) / rx.image_distance * ARCMIN


def figures(name: str) -> dict[str, float | tuple[float, float]]:
    """The figures of shipped lens ``name`` (module docstring); angles in degrees or arcmin."""
    rx = Prescription(shipped_prescription(name))
    bank = load_lens(name).bank
    ref = rx.reference_wavelength
    red, blue = max(rx.wavelengths), min(rx.wavelengths)
    half, corner = rx.display_mm[0] / 2, math.hypot(*rx.display_mm) / 2
    m = real_magnification(rx, ref)
    out: dict[str, float | tuple[float, float]] = {"focal length at 550 nm (mm)": paraxial(rx, ref).efl,
           "field of view, width / diagonal (deg)": (2 * math.degrees(_angle(rx, ref, half)),
                                                     2 * math.degrees(_angle(rx, ref, corner)))}
    for where, h in (("mid-edge", half), ("corner", corner)):
        _, Y, _ = chief_ray(rx, ref, np.array([h]))
        out[f"distortion at the {where} (%)"] = (float(Y[0]) / (m * h) - 1) * 100
    for where, h in (("mid-edge", half), ("corner", corner)):
        out[f"lateral colour {blue:g} - {red:g} nm at the {where} (arcmin)"] = (
            (_angle(rx, blue, h) - _angle(rx, red, h)) * ARCMIN)
    li = rx.wavelengths.index(ref)
    for where, (u, v) in FIELDS.items():
        out[f"RMS PSF radius at 550 nm, {where} (arcmin)"] = psf_rms_arcmin(bank, rx, li, *_nearest(bank, u, v))
    out["display pixel at 1024 px across, on axis (arcmin)"] = m * rx.display_mm[0] / 1024 / rx.image_distance * ARCMIN
    out["path efficiency"] = rx.efficiency
    return out


def plot(path: Path, names: list[str]) -> None:
    """PSF picture: a row per lens, a column per field of :data:`FIELDS`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(names), len(FIELDS), figsize=(3.0 * len(FIELDS), 3.0 * len(names)), squeeze=False)
    for row, name in enumerate(names):
        rx = Prescription(shipped_prescription(name))
        bank = load_lens(name).bank
        scale = real_magnification(rx, rx.reference_wavelength) / rx.image_distance * ARCMIN   # arcmin per display mm
        for col, (where, (u, v)) in enumerate(FIELDS.items()):
            iy, ix = _nearest(bank, u, v)
            k = bank.psf.shape[-1]
            pitch = bank.psf_pitch_mm[:, iy, ix].double().numpy()
            half = float(pitch.max()) * (k // 2 + 0.5) * scale        # the widest primary's window, arcmin
            grid = np.linspace(-half, half, 161)
            rgb = np.zeros((grid.size, grid.size, 3))
            for li in range(3):   # each primary resampled (nearest sample) onto the common grid
                idx = np.rint(grid / (pitch[li] * scale)).astype(int) + k // 2
                inside = (idx >= 0) & (idx < k)
                p = bank.psf[li, iy, ix].double().numpy()
                img = p[np.clip(idx, 0, k - 1)][:, np.clip(idx, 0, k - 1)] * inside[:, None] * inside[None, :]
                rgb[..., li] = img / (pitch[li] * scale) ** 2          # density per arcmin^2
            rgb = np.sqrt(rgb / rgb.max())
            ax = axes[row, col]
            ax.imshow(rgb, extent=(-half, half, half, -half), interpolation="nearest")
            ax.set_title(f"{name}, {where}\nfield ({float(bank.field_x[ix]):.2f}, {float(bank.field_y[iy]):.2f})",
                         fontsize=9)
            ax.set_xlabel("arcmin", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    print(f"wrote {path}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--png", type=Path, help="write the PSF picture here")
    args = ap.parse_args(argv)
    names = list(SHIPPED_LENSES)
    table = {name: figures(name) for name in names}
    print("| | " + " | ".join(names) + " |")
    print("|---|" + "---:|" * len(names))
    for key in table[names[0]]:
        cells = [" / ".join(f"{x:.2f}" for x in v) if isinstance(v, tuple) else f"{v:.3g}" if abs(v) < 1 else f"{v:.2f}"
                 for v in (table[n][key] for n in names)]
        print(f"| {key} | " + " | ".join(cells) + " |")
    if args.png:
        plot(args.png, names)


if __name__ == "__main__":
    main()
