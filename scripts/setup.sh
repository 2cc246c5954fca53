#!/usr/bin/env bash
# Creates .venv (if needed) and installs controlgs-adapter with the demo and test extras.
# CPU torch 2.13.0 is pinned by constraints.txt; pyproject keeps a range for users elsewhere.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt torch==2.13.0
.venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt -e ".[demo,test]"
# lpips only for its LPIPS head weights and as the tests' reference; --no-deps: its torchvision
# requirement would replace the CPU torch (controlgs-adapter never imports torchvision)
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps lpips==0.1.4
