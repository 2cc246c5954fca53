#!/usr/bin/env bash
# Mutation testing with cosmic-ray: a random sample of mutants of controlgs_adapter, backends and downstream, each
# run against the tests that executed the mutated lines. Not part of the test suite; see tests/README.md,
# "Mutation testing".
#
#   scripts/mutation/run.sh [--sample N] [--torch K] [--seed S] [--rev REV] [--max-tests M] [--work DIR]
#
#   --sample N     mutants to run (default 100), of which --torch K from the torch/* operators (default 20)
#   --seed S       random seed of the draw (default 1): the same seed on the same commit draws the same mutants
#   --rev REV      the commit to mutate (default HEAD), in a scratch copy: cosmic-ray rewrites the files it
#                  mutates, so it never runs in this checkout
#   --max-tests M  at most M covering tests per mutant, the most focused first (default 60)
#   --work DIR     where the copy, coverage data, session and report go (default a new /tmp/controlgs-mutation.*);
#                  run again with the same DIR to go on where an interrupted run stopped (steps already done
#                  are kept: the copy, the coverage data, the session and its results)
#
# Steps: (1) the whole suite once under coverage.py, one context per test (the only full run; tests already
# failing there are never selected); (2) cosmic-ray init; (3) the draw (scripts/mutation/sample.py); (4) cosmic-ray
# exec, whose test command is scripts/mutation/select_tests.py; then scripts/mutation/report.py.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
VENV=${VENV:-$ROOT/.venv}
SAMPLE=100 TORCH=20 SEED=1 REV=HEAD WORK="" MAX_TESTS=60
while [ $# -gt 0 ]; do
    case "$1" in
        --sample) SAMPLE=$2; shift 2 ;;
        --torch) TORCH=$2; shift 2 ;;
        --seed) SEED=$2; shift 2 ;;
        --rev) REV=$2; shift 2 ;;
        --max-tests) MAX_TESTS=$2; shift 2 ;;
        --work) WORK=$2; shift 2 ;;
        *) sed -n '2,20p' "$0" >&2; exit 2 ;;
    esac
done
if ! { "$VENV/bin/cosmic-ray" operators 2>/dev/null || true; } | grep '^torch/' >/dev/null; then
    echo "cosmic-ray or its torch operators are missing; install them with" >&2
    echo "  $VENV/bin/pip install -e '.[mutation]'   (or: $VENV/bin/pip install 'cosmic-ray>=8.7,<9' 'coverage>=7.3')" >&2
    echo "  $VENV/bin/pip install --no-deps -e scripts/mutation/operators" >&2
    exit 2
fi
export PATH="$VENV/bin:$PATH" OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONDONTWRITEBYTECODE=1
export MUTATION_MAX_TESTS=$MAX_TESTS
CONFIG=scripts/mutation/cosmic-ray.toml
WORK=${WORK:-$(mktemp -d /tmp/controlgs-mutation.XXXXXX)}
mkdir -p "$WORK"
WORK=$(cd "$WORK" && pwd)
TREE=$WORK/tree
export MUTATION_WORK=$WORK

if [ ! -e "$TREE" ]; then
    COMMIT=$(git -C "$ROOT" rev-parse "$REV")
    mkdir -p "$TREE"
    git -C "$ROOT" archive "$COMMIT" | tar -x -C "$TREE"
    # this checkout's runner, whatever REV holds
    rm -rf "$TREE/scripts/mutation" && mkdir -p "$TREE/scripts/mutation"
    cp "$ROOT"/scripts/mutation/*.py "$ROOT"/scripts/mutation/*.toml "$TREE/scripts/mutation/"
    # a repository of its own, so that select_tests.py finds the mutated lines with git diff
    git -C "$TREE" init -q && git -C "$TREE" add -A
    git -C "$TREE" -c user.name=mutation -c user.email=mutation@localhost commit -qm "$COMMIT"
else
    echo "going on in $WORK"
    # an interrupted run can leave its last mutation in the scratch copy
    git -C "$TREE" diff --quiet -- controlgs_adapter backends downstream \
        || git -C "$TREE" restore --worktree -- controlgs_adapter backends downstream
fi
cd "$TREE"
echo "mutating $(git log -1 --format=%s) in $TREE"
if [ ! -f "$WORK/baseline.json" ]; then
    echo "1/4 the whole suite under coverage, one context per test ($WORK/coverage.log)"
    MUTATION_BASELINE=$WORK/baseline.json PYTHONPATH="$TREE:$TREE/scripts/mutation" \
        python -m coverage run --data-file="$WORK/coverage.db" --source=controlgs_adapter,backends,downstream \
        -m pytest -q -p no:cacheprovider -p pytest_contexts >"$WORK/coverage.log" 2>&1 || true
    tail -n 1 "$WORK/coverage.log"
    [ -f "$WORK/baseline.json" ] || { echo "the coverage run did not finish: $WORK/coverage.log" >&2; exit 1; }
    rm -f "$WORK/focus.json"
fi
[ -f "$WORK/focus.json" ] || python scripts/mutation/select_tests.py --index
if [ ! -f "$WORK/session.sqlite" ]; then
    echo "2/4 cosmic-ray init (every mutant of every module)"
    cosmic-ray init "$CONFIG" "$WORK/session.tmp"
    echo "3/4 the draw"
    python scripts/mutation/sample.py "$CONFIG" "$WORK/session.tmp" --sample "$SAMPLE" --torch "$TORCH" --seed "$SEED"
    mv "$WORK/session.tmp" "$WORK/session.sqlite"
fi
echo "4/4 cosmic-ray exec ($WORK/session.sqlite)"
cosmic-ray exec "$CONFIG" "$WORK/session.sqlite"
python scripts/mutation/report.py "$WORK/session.sqlite" | tee "$WORK/report.txt"
echo "report: $WORK/report.txt"
