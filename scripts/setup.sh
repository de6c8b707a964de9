#!/usr/bin/env bash
# Sets up rlpipe in ./.venv on a fresh machine with Python 3.11: the CPU build of torch first (it
# lies on this machine's disk; any other torch spec pulls a multi-GB CUDA build), then the rest.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-$(command -v python3.11 || command -v python3)}"
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q torch==2.13.0
# ray: collector.backend=ray and its tests (tests/test_ray.py)
.venv/bin/python -m pip install -q -e ".[test,ray]"
echo "rlpipe is set up in .venv (activate with: source .venv/bin/activate)"
