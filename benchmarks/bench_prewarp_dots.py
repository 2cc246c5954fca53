"""Where the light of a dot lands through lens pre-warp + optics: the pre-warp accuracy table.

A white Gaussian dot (sigma 1 px) is rendered at every point of a 0.1 grid over [-0.8, 0.8]^2 and at the
corners (+-0.85, +-0.85) (on a non-square image the field's vertical extent follows the image's), sent
through ``{"lens", "optics"}`` in float64, and each display primary's light centroid in a window around
the dot is compared with the dot's centre. Printed per pre-warp variant, optics mode and size: the worst
primary's error (px) over the field and, in brackets, the error at (0.6, -0.5).

    python benchmarks/bench_prewarp_dots.py                  # sizes 256, 96 and 96x54 (minutes at 256 px)
    python benchmarks/bench_prewarp_dots.py --sizes 96 96x54
    python benchmarks/bench_prewarp_dots.py --lens compact    # any lens spec that `controlgs train --lens` takes
"""
from __future__ import annotations

import argparse

import torch

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream.color import linear_to_srgb, rgb_to_primaries, srgb_to_linear
from controlgs_adapter.downstream.lens import DisplayLUTMap
from controlgs_adapter.downstream.optics.lenses import DEFAULT_LENS, Lens, effects_for_lens, load_lens
from controlgs_adapter.downstream.pipeline import Pipeline

D = torch.float64
CORNERS = [(0.85, 0.85), (-0.85, -0.85), (0.85, -0.85), (-0.85, 0.85)]
GRID = [(round(0.1 * i, 1), round(0.1 * j, 1)) for j in range(-8, 9) for i in range(-8, 9)] + CORNERS
PROBE = (0.6, -0.5)


def dot_errors(pipe: Pipeline, h: int, w: int, field: list[tuple[float, float]]) -> torch.Tensor:
    """``[dots, 3]`` distance (px) of each primary's eye centroid from the dot's centre."""
    yy, xx = torch.meshgrid(torch.arange(h, dtype=D) + 0.5, torch.arange(w, dtype=D) + 0.5, indexing="ij")
    centres = [((u + 1) / 2 * w, (v + 1) / 2 * h) for u, v in field]
    r = max(6, min(h, w) // 8)
    errs = []
    with torch.no_grad():
        for start in range(0, len(centres), 32):
            chunk = centres[start:start + 32]
            dots = torch.stack([0.5 * torch.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 2).expand(3, h, w) for cx, cy in chunk])
            prim = rgb_to_primaries(srgb_to_linear(pipe(linear_to_srgb(dots), RuntimeState())))
            for k, (cx, cy) in enumerate(chunk):
                m = prim[k] * (((xx - cx).abs() < r) & ((yy - cy).abs() < r))
                s = m.sum((1, 2))
                errs.append(torch.hypot((m * xx).sum((1, 2)) / s - cx, (m * yy).sum((1, 2)) / s - cy))
    return torch.stack(errs)


def variants(mode: str, lens: Lens | None = None) -> dict[str, Pipeline]:
    """Through ``lens`` (None: the shipped Cardboard lens): the default pre-warp (fitted tables per display
    size, 2 x 2 samples per display pixel) and the same table fitted at 256 px only, sampled once per
    display pixel."""
    default = Pipeline.from_config(effects_for_lens({"lens": True, "optics": {"mode": mode}}, lens)).double()
    single = Pipeline.from_config(effects_for_lens({"lens": {"supersample": 1}, "optics": {"mode": mode}}, lens)).double()
    lut = single["lens"].map
    main = {mode: (getattr(lut, f"displacement_{mode}"), getattr(lut, f"gain_{mode}"))}
    single["lens"].map = DisplayLUTMap(main, lut.display_mm, meta=lut.meta).follow(single["optics"]).double()
    return {"fitted per display size, 2 x 2 samples (default)": default,
            "fitted at 256 px only, one sample per display pixel": single}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=["256", "96", "96x54"], help="N or WxH")
    ap.add_argument("--modes", nargs="+", default=["distortion", "exact"], choices=["distortion", "exact"])
    ap.add_argument("--lens", default=DEFAULT_LENS, help="a shipped lens name or a lens file (default: %(default)s)")
    args = ap.parse_args(argv)
    lens = load_lens(args.lens)
    torch.set_num_threads(1)
    sizes = [(int(s.split("x")[1]), int(s.split("x")[0])) if "x" in s else (int(s), int(s)) for s in args.sizes]
    print("| pre-warp | optics | " + " | ".join(args.sizes) + " |")
    print("|---|---|" + "---:|" * len(sizes))
    for mode in args.modes:
        for name, pipe in variants(mode, lens).items():
            cells = []
            for h, w in sizes:
                field = GRID if h == w else [(u, v * h / w) for u, v in GRID]
                err = dot_errors(pipe, h, w, field)
                probe = field.index(PROBE if h == w else (PROBE[0], PROBE[1] * h / w))
                cells.append(f"{float(err.max()):.3f} ({float(err[probe].max()):.3f})")
            print(f"| {name} | {mode} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
