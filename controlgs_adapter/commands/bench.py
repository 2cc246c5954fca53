"""``controlgs bench``: accuracy vs time on the built-in scene (printed; ``--doc`` writes ``docs/benchmarks/accuracy-time.md``).

The command line only: what is measured is :mod:`controlgs_adapter.benchmarking.accuracy_time`,
the report :mod:`controlgs_adapter.benchmarking.report`.
"""

from __future__ import annotations

import argparse
import datetime
import math
import shlex
import time
from pathlib import Path
from typing import Any

from controlgs_adapter.benchmarking.accuracy_time import DEFAULT_ITERATIONS, QUICK_ITERATIONS, BenchSettings, run_bench
from controlgs_adapter.benchmarking.report import format_report, write_report

DOC_OUT = Path("docs") / "benchmarks" / "accuracy-time.md"


def add_parser(sub: "argparse._SubParsersAction") -> None:
    from .demo import DEFAULT_RESOLUTION

    p = sub.add_parser("bench", help="accuracy vs time on the built-in scene: phases, knobs, overhead (printed; "
                                      "--doc writes docs/benchmarks/accuracy-time.md)")
    p.add_argument("--out", type=Path, default=None, help="Markdown report to write (default: print only)")
    p.add_argument("--doc", dest="out", action="store_const", const=DOC_OUT, help=f"write {DOC_OUT}")
    p.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION, help="native resolution S (pixels)")
    p.add_argument("--iterations", type=int, default=None,
                   help=f"training iterations per knob (default {DEFAULT_ITERATIONS}; {QUICK_ITERATIONS} with --quick)")
    p.add_argument("--test-views", type=int, default=None, help="test views of the quality evaluation (default 4; 1 with --quick)")
    p.add_argument("--quick", action="store_true", help="about 2 minutes: fewer iterations, one test view, a 2 x 2 grid")
    p.add_argument("--variant", choices=("ar", "vr"), default="ar", help="built-in scene: object-centric AR or immersive VR")
    p.add_argument("--seed", type=int, default=BenchSettings.seed,
                   help=f"training seed of every knob's adapter (default {BenchSettings.seed}, TrainConfig's)")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    p.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace) -> BenchSettings:
    """:class:`BenchSettings` of the command line (``--quick`` changes only what is not given)."""
    quick: dict[str, Any] = {"iterations": QUICK_ITERATIONS, "phase_iterations": 6, "repeats": 5, "test_views": 1,
             "downsample": (1.0, 4.0), "power_saving": (0.0, 0.6)} if args.quick else {}
    if args.iterations is not None:
        quick["iterations"] = args.iterations
    if args.test_views is not None:
        quick["test_views"] = args.test_views
    return BenchSettings(resolution=args.resolution, variant=args.variant, seed=args.seed, **quick)


def run(args: argparse.Namespace) -> int:
    """Measure, print the report, write it to ``--out`` / ``--doc`` if given."""
    from .common import check_options, check_out_path

    check_options(args)
    if args.out is not None:
        check_out_path(args.out, "--out", folder=False)  # before the measurements
    settings = settings_from_args(args)
    t0 = time.perf_counter()
    result = run_bench(settings, progress=args.progress)
    result.info["date"] = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = format_report(result, "controlgs " + " ".join(shlex.quote(a) for a in args.argv))
    text += f"\nTotal time of this run: {math.ceil(time.perf_counter() - t0)} s.\n"
    print(text)
    if args.out is not None:
        print(f"wrote {write_report(text, args.out)}")
    return 0
