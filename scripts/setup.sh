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
# ray: collector.backend=ray and its tests (tests/test_ray.py); bench: py-spy for `rlpipe bench profile`;
# tune: Optuna for `rlpipe tune` (tests/test_tune.py); docs: mkdocs for the documentation site (tests/test_docs.py);
# wandb, mlflow: logger=wandb|mlflow (tests/test_loggers.py); box2d: LunarLander and BipedalWalker (tests/test_envs.py)
.venv/bin/python -m pip install -q -e ".[test,ray,bench,tune,docs,wandb,mlflow,box2d]"
# The report page's browser test drives Debian's chromium through Playwright (Playwright's own browser
# download is not reachable here). Installed where apt-get and root are at hand; elsewhere the test
# says it skipped and why.
if ! command -v chromium >/dev/null 2>&1; then
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
      || echo "setup: could not install chromium with apt-get; the report page's browser test will be skipped" >&2
  else
    echo "setup: chromium not installed (needs apt-get as root); the report page's browser test will be skipped" >&2
  fi
fi
echo "rlpipe is set up in .venv (activate with: source .venv/bin/activate)"
