"""rlpipe installs as a dependency does: from its wheel, into a fresh venv, and runs there as ``rlpipe`` and as
``python -m rlpipe``, importing its own installed files (not this checkout's)."""

from __future__ import annotations

import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_wheel_installs_into_a_fresh_venv_and_runs_as_rlpipe_and_python_m_rlpipe(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", str(ROOT),
                    "-w", str(tmp_path / "dist")], check=True, capture_output=True, cwd=tmp_path)
    wheel, = (tmp_path / "dist").glob("rlpipe-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "rlpipe/__main__.py" in names and "rlpipe/__init__.py" not in names  # a namespace with its entry point
    assert {"rlpipe/pipelines/py.typed", "rlpipe/presets/sac.yaml", "rlpipe/envs/minitaur.py"} <= set(names)
    assert not [n for n in names if "/results/" in n or n.startswith("tests/")]  # no benchmark results, no tests

    env = tmp_path / "venv"
    venv.create(env, with_pip=False)
    python = env / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps", str(wheel)],
                   check=True, capture_output=True)
    # its dependencies (torch, TorchRL, ...) from this venv's site-packages, as a path only: this checkout's editable
    # install (a .pth there) is not read, so rlpipe can come from the wheel alone
    site = Path(subprocess.check_output([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                        text=True).strip())
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")

    where = subprocess.run([str(python), "-c", "import rlpipe.pipelines, rlpipe.scripts.cli; print(rlpipe.pipelines.__file__)"],
                           capture_output=True, text=True, cwd=tmp_path)
    assert where.returncode == 0, where.stderr
    assert Path(where.stdout.strip()).is_relative_to(env)
    for command in ([str(python), "-m", "rlpipe", "presets"], [str(env / "bin" / "rlpipe"), "presets"]):
        done = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        assert "sac-minitaur" in done.stdout
    bad = subprocess.run([str(python), "-m", "rlpipe", "train", "no-such-preset"], capture_output=True, text=True,
                         cwd=tmp_path)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "no-such-preset" in bad.stderr
