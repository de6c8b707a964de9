"""The README's promises: its Python examples run as written and print what they say, and its
commands are the real ones."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_blocks() -> list[str]:
    # the examples of the Python section (the run-directory snippet needs a finished run's path)
    return [b for b in re.findall(r"```python\n(.*?)```", README.read_text(), re.S) if "RUN_DIR" not in b]


def _run(block: str, cwd: Path) -> list[str]:
    proc = subprocess.run([sys.executable, "-c", block], cwd=cwd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    # TorchRL logs INFO lines to stdout too; the example's own lines are the unadorned ones.
    return [line for line in proc.stdout.strip().splitlines() if not line.startswith("\x1b")]


def test_readme_has_the_python_examples_it_promises():
    assert len(_python_blocks()) == 4


def test_the_first_example_prints_the_runs_own_final_return(tmp_path):
    lines = _run(_python_blocks()[0], tmp_path)
    value, run_dir = lines[-1].split()
    summary = json.loads((tmp_path / run_dir / "summary.json").read_text())
    assert float(value) == pytest.approx(summary["final_average_return"])
    assert (tmp_path / run_dir / "policy" / "policy.pt2").exists()


def test_the_own_env_example_uses_a_batched_plain_env_a_logger_and_a_trigger(tmp_path):
    lines = _run(_python_blocks()[1], tmp_path)
    assert lines[-1] == "Pendulum-v1 400"
    assert [line.split(":")[0] for line in lines[:-1]] == ["iteration 200", "iteration 400"]  # the trigger
    assert (tmp_path / "runs/readme-logs/td3/scalars/average_return.csv").exists()  # the logger


def test_the_own_networks_example_trains_each_algorithm(tmp_path):
    assert _run(_python_blocks()[2], tmp_path)[-3:] == ["200", "200", "200"]


def test_the_own_loop_example_collects_updates_and_exports(tmp_path):
    assert _run(_python_blocks()[3], tmp_path)[-1] == "MultiSyncCollector 1200 800 policy.onnx"
    assert (tmp_path / "runs/readme-own-loop/policy.pt2").exists()


def test_readme_opens_with_setup_and_test_commands():
    head = README.read_text().split("```bash", 1)[1].split("```", 1)[0]
    commands = [line.split("#")[0].strip() for line in head.strip().splitlines()]
    assert commands[0] == "bash scripts/setup.sh && .venv/bin/rlpipe train sac"
    assert commands[1] == "bash scripts/setup.sh && .venv/bin/python -m pytest -q"
    ci = (README.parent / ".ci/run").read_text()
    assert commands[1] in ci
