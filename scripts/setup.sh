#!/usr/bin/env bash
# Creates .venv (if needed) and installs controlgs-adapter with the demo, test and cvvdp extras.
# CPU torch 2.13.0 is pinned by constraints.txt; pyproject keeps a range for users elsewhere.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt torch==2.13.0
.venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt -e ".[demo,test,cvvdp]"
# lpips only for its LPIPS head weights and as the tests' reference; --no-deps: its torchvision
# requirement would replace the CPU torch (controlgs-adapter never imports torchvision)
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps lpips==0.1.4
# ColorVideoVDP for every report, --no-deps for the same reason (its needs come with the cvvdp extra above;
# controlgs_adapter.cvvdp_shim stands in for the torchvision and huggingface_hub names it imports)
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps -c constraints.txt cvvdp
# the viewer's browser test drives Debian's headless Chromium: installed only as root with apt-get, when missing
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null && ! { command -v chromium && command -v chromedriver; } >/dev/null 2>&1; then
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -q --no-install-recommends chromium chromium-driver fonts-liberation >/dev/null 2>&1 \
        || { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q --no-install-recommends chromium chromium-driver fonts-liberation >/dev/null 2>&1; } \
        || echo "setup.sh: could not install chromium + chromium-driver; the viewer's browser test will be skipped" >&2
fi
