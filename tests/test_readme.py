"""The README's promises: it opens with the set-up and test commands CI runs, its Python example runs as written
and prints what it says, and its links lead to files that exist. (The examples that moved to the documentation
site run in tests/test_docs.py, with their checks beside them on each page.)"""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_the_python_example_prints_the_runs_own_final_return(tmp_path):
    blocks = _python_blocks()
    assert len(blocks) == 1
    proc = subprocess.run([sys.executable, "-c", blocks[0]], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    # TorchRL logs INFO lines to stdout too; the example's own lines are the unadorned ones.
    lines = [line for line in proc.stdout.strip().splitlines() if not line.startswith("\x1b")]
    value, run_dir = lines[-1].split()
    summary = json.loads((tmp_path / run_dir / "summary.json").read_text())
    assert float(value) == pytest.approx(summary["final_average_return"])
    assert (tmp_path / run_dir / "policy" / "policy.pt2").exists()


def test_readme_opens_with_setup_and_test_commands():
    head = README.read_text().split("```bash", 1)[1].split("```", 1)[0]
    commands = [line.split("#")[0].strip() for line in head.strip().splitlines()]
    assert commands[0] == "bash scripts/setup.sh && .venv/bin/rlpipe train sac"
    assert commands[1] == "bash scripts/setup.sh && .venv/bin/python -m pytest -q"
    ci = (ROOT / ".ci/run").read_text()
    assert commands[1] in ci


def test_readmes_links_lead_to_files_that_exist():
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", README.read_text())
    local = [link for link in links if "://" not in link]
    assert any(link.startswith("docs/") for link in local)
    assert [link for link in local if not (ROOT / link).exists()] == []
