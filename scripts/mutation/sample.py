"""Draw a random sample from a cosmic-ray session: every other pending mutant is marked skipped.

    python scripts/mutation/sample.py CONFIG SESSION --sample 100 --torch 20 --seed 1

Before drawing, two kinds of mutant leave the pool (skipped, with the reason as their output):
- operators matched by ``exclude-operators`` under ``[cosmic-ray.filters.operators-filter]`` in CONFIG (the same
  key cosmic-ray's own cr-filter-operators reads);
- mutations inside a type annotation: the package is written with ``from __future__ import annotations``, so an
  annotation is never evaluated and ``int | None`` -> ``int - None`` cannot change behaviour.

Then ``--torch`` mutants are drawn from the torch/* operators (few sites, the bugs this code is prone to) and the
rest of ``--sample`` from all other operators, with random.Random(seed) over the session sorted by file,
operator and occurrence: the same seed on the same commit draws the same mutants.
"""

from __future__ import annotations

import argparse
import random
import re
from collections import defaultdict
from pathlib import Path

import parso
from cosmic_ray.config import load_config
from cosmic_ray.work_db import WorkDB, use_db
from cosmic_ray.work_item import WorkerOutcome, WorkResult


def annotation_spans(path: Path) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """(start, end) of every parameter, return and variable annotation in a module."""
    spans = []

    def walk(node):
        if node.type == "param" and getattr(node, "annotation", None) is not None:
            spans.append((node.annotation.start_pos, node.annotation.end_pos))
        elif node.type in ("funcdef", "async_funcdef") and getattr(node, "annotation", None) is not None:
            spans.append((node.annotation.start_pos, node.annotation.end_pos))
        elif node.type == "annassign":
            spans.append((node.children[1].start_pos, node.children[1].end_pos))
        for child in getattr(node, "children", ()):
            walk(child)

    walk(parso.parse(path.read_text(encoding="utf-8")))
    return spans


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("config")
    ap.add_argument("session")
    ap.add_argument("--sample", type=int, default=100, help="mutants to run in all (default 100)")
    ap.add_argument("--torch", type=int, default=20, help="of which from the torch/* operators (default 20)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    excluded = load_config(args.config).sub("filters", "operators-filter").get("exclude-operators", ())
    exclude = re.compile("|".join(f"(?:{e})" for e in excluded)) if excluded else None
    with use_db(args.session, mode=WorkDB.Mode.open) as db:
        items = sorted(db.pending_work_items, key=lambda w: (str(w.mutations[0].module_path),
                                                               w.mutations[0].operator_name, w.mutations[0].occurrence))
        spans: dict[Path, list] = {}
        skip: dict[str, list[str]] = defaultdict(list)
        torch_pool, core_pool = [], []
        for item in items:
            m = item.mutations[0]
            if exclude and exclude.match(m.operator_name):
                skip["operator excluded by the configuration"].append(item.job_id)
                continue
            if m.module_path not in spans:
                spans[m.module_path] = annotation_spans(m.module_path)
            if any(a <= tuple(m.start_pos) and tuple(m.end_pos) <= b for a, b in spans[m.module_path]):
                skip["inside a type annotation (never evaluated)"].append(item.job_id)
                continue
            (torch_pool if m.operator_name.startswith("torch/") else core_pool).append(item)
        rng = random.Random(args.seed)
        n_torch = min(args.torch, len(torch_pool))
        chosen = rng.sample(torch_pool, n_torch) + rng.sample(core_pool, min(args.sample - n_torch, len(core_pool)))
        keep = {w.job_id for w in chosen}
        skip["not drawn"] = [w.job_id for w in torch_pool + core_pool if w.job_id not in keep]
        for reason, job_ids in skip.items():
            db.set_multiple_results(job_ids, WorkResult(output=reason, worker_outcome=WorkerOutcome.SKIPPED))
    for reason, job_ids in skip.items():
        print(f"skipped, {reason}: {len(job_ids)}")
    print(f"drawn: {len(chosen)} ({n_torch} torch/*, {len(chosen) - n_torch} others) of "
          f"{len(torch_pool)} + {len(core_pool)}, seed {args.seed}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
