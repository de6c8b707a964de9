"""The code passes ruff with the project's settings (pyproject.toml): unused or missing names,
import order, likely bugs (bugbear), outdated syntax. CI runs the suite, so CI lints."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing():
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "."], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]


def test_the_layering_contracts_hold():
    """pyproject.toml's [tool.importlinter] contracts: the rooms' layering (a higher room may import a lower
    one, never the reverse; TYPE_CHECKING-only imports aside), modules/ and envs/ free of pipelines,
    nothing under pipelines importing scripts, the algorithms independent, no import circle in a package."""
    lint_imports = Path(sys.executable).with_name("lint-imports")
    assert lint_imports.exists(), "import-linter is missing: pip install -e '.[test]'"
    proc = subprocess.run([str(lint_imports), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-2000:]
    assert "0 broken" in proc.stdout, proc.stdout[-3000:]
