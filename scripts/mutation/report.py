"""Summarise a cosmic-ray session run by scripts/mutation/run.sh: the score and every survivor.

    python scripts/mutation/report.py SESSION [--killed]

Score = killed / (killed + survived) over the drawn mutants (skipped ones left out); a timeout counts as
killed and is listed. Each survivor: file:line, operator, the mutated line and which tests ran against it.
"""

from __future__ import annotations

import argparse
from collections import Counter

from cosmic_ray.work_db import WorkDB, use_db
from cosmic_ray.work_item import TestOutcome, WorkerOutcome


def _changed(diff: str) -> str:
    minus = [ln[1:].strip() for ln in diff.splitlines() if ln.startswith("-") and not ln.startswith("---")]
    plus = [ln[1:].strip() for ln in diff.splitlines() if ln.startswith("+") and not ln.startswith("+++")]
    return f"{' / '.join(minus)}  ->  {' / '.join(plus)}"


def _selection(output: str) -> str:
    for line in (output or "").splitlines():
        if line.startswith(("ran ", "no test executes")):
            return line
    return ""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("session")
    ap.add_argument("--killed", action="store_true", help="list the killed mutants too")
    args = ap.parse_args()
    with use_db(args.session, mode=WorkDB.Mode.open) as db:
        done = [(item, result) for item, result in db.completed_work_items if result.worker_outcome != WorkerOutcome.SKIPPED]
        pending = sum(1 for _ in db.pending_work_items)
    tally: Counter[str] = Counter()
    rows = []
    for item, result in sorted(done, key=lambda ir: (str(ir[0].mutations[0].module_path), ir[0].mutations[0].start_pos)):
        m = item.mutations[0]
        where = f"{m.module_path}:{m.start_pos[0]}"
        if result.worker_outcome != WorkerOutcome.NORMAL:
            tally[result.worker_outcome.value] += 1
            rows.append(("ERROR", where, m.operator_name, (result.output or "").strip().splitlines()[-1:]))
            continue
        outcome = result.test_outcome
        if outcome == TestOutcome.KILLED and result.output == "timeout":
            tally["timeout"] += 1
        tally[outcome.value] += 1
        if outcome == TestOutcome.SURVIVED or (args.killed and outcome == TestOutcome.KILLED) or result.output == "timeout":
            label = "TIMEOUT" if result.output == "timeout" else outcome.value.upper()
            rows.append((label, where, m.operator_name, _changed(result.diff or ""), _selection(result.output)))
    killed, survived = tally["killed"], tally["survived"]
    scored = killed + survived
    print(f"{len(done)} mutants run, {pending} pending: {killed} killed ({tally['timeout']} by timeout), "
          f"{survived} survived, {tally['incompetent']} incompetent, "
          f"{sum(v for k, v in tally.items() if k in ('exception', 'abnormal', 'no-test'))} not run")
    if scored:
        print(f"score: {killed}/{scored} = {100.0 * killed / scored:.1f}% killed")
    for row in rows:
        print("\n" + "  ".join(str(x) for x in row[:3]))
        for extra in row[3:]:
            if extra:
                print(f"    {extra}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
