"""Rebuild the shipped compact lens's PSF bank and pre-warp LUT from its prescription.

Reads ``controlgs_adapter/data/compact_prescription.json`` and writes, next to it,
``compact_psf_bank.safetensors`` (30 x 30 fields, the ``controlgs optics build-bank`` defaults) and
``compact_prewarp_lut.safetensors`` (the ``controlgs optics fit-prewarp`` defaults: distortion and exact
modes, radiance, 64 to 256 px). The same two commands, run by hand:

    controlgs optics build-bank --lens compact --out controlgs_adapter/data/compact_psf_bank.safetensors
    controlgs optics fit-prewarp --lens controlgs_adapter/data/compact_psf_bank.safetensors \\
        --out controlgs_adapter/data/compact_prewarp_lut.safetensors

About 1 + 3 minutes on 2 CPU cores. ``--out-dir`` writes both files elsewhere (the shipped ones stay).

    python scripts/build_compact_lens.py [--out-dir DIR]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.generate import build_bank
from controlgs_adapter.downstream.optics.lenses import SHIPPED_LENSES, shipped_prescription
from controlgs_adapter.downstream.optics.stage import PSFOptics
from controlgs_adapter.downstream.prewarp_fit import fit_bank_prewarp

DATA = Path(__file__).resolve().parents[1] / "controlgs_adapter" / "data"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out-dir", type=Path, default=DATA, help="where the bank and LUT go (default: the package data)")
    args = ap.parse_args(argv)
    entry = SHIPPED_LENSES["compact"]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    build_bank(shipped_prescription("compact"), progress=True).save(args.out_dir / entry.bank)
    print(f"wrote {args.out_dir / entry.bank} in {time.perf_counter() - t0:.0f} s", flush=True)
    t0 = time.perf_counter()   # fitted to the bank as stored (the LUT records the stored bank's fingerprint)
    fit_bank_prewarp(PSFOptics(PSFBank.load(args.out_dir / entry.bank))).save(args.out_dir / entry.prewarp)
    print(f"wrote {args.out_dir / entry.prewarp} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
