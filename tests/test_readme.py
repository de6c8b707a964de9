"""The README's promises: its Python example runs as written, and its commands are the real ones."""

import re
import subprocess
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_readme_python_example_runs(tmp_path):
    example = _python_blocks()[0]
    proc = subprocess.run([sys.executable, "-c", example], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    # TorchRL logs INFO lines to stdout too; the example's own lines are the unadorned ones.
    lines = [line for line in proc.stdout.strip().splitlines() if not line.startswith("\x1b")]
    assert float(lines[0].split()[0]) > 0  # an average return
    assert int(lines[-1]) == 500  # the second pipeline made one update per iteration
    assert (tmp_path / "runs/readme-dqn/policy/policy.pt2").exists()


def test_readme_opens_with_setup_and_test_commands():
    head = README.read_text().split("```bash", 1)[1].split("```", 1)[0]
    commands = [line.split("#")[0].strip() for line in head.strip().splitlines()]
    assert commands[0] == "bash scripts/setup.sh && .venv/bin/rlpipe train sac"
    assert commands[1] == "bash scripts/setup.sh && .venv/bin/python -m pytest -q"
    ci = (README.parent / ".ci/run").read_text()
    assert commands[1] in ci
