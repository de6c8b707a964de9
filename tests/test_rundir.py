"""A run directory against crashes, full disks, refused writes and a second writer: real `rlpipe`
processes, killed, held (SIGSTOP) or refused a write at exact points (``RLPIPE_FAULT``), never timed.

Each process costs seconds of start-up (torch + TorchRL imports), so one trained run is shared
(module fixture) and copied, and where a second command only has to be refused, it runs in this
process through the CLI's ``main()`` (the lock it meets is still the other process's).
"""

from __future__ import annotations

import contextlib
import csv
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rlpipe.pipelines.artifacts import checkpoint as ckpt

RLPIPE = [sys.executable, "-m", "rlpipe.scripts.cli"]
N = 200
TINY = [f"num_iterations={N}", "initial_collect_steps=100", "eval_interval=100", "num_eval_episodes=1",
        "log_interval=100", "checkpoint_interval=100", "policy_save_interval=100"]
DEADLINE_S = 240  # generous: the machine is shared; nothing waits on time, only on events


def start(args, cwd: Path, fault: str | None = None) -> subprocess.Popen:
    """``rlpipe ARGS`` in its own process group (a fault's signal reaches the run and its workers only)."""
    return subprocess.Popen([*RLPIPE, *map(str, args)], cwd=cwd, env={**os.environ, "RLPIPE_FAULT": fault or ""},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def finish(proc: subprocess.Popen, timeout: float = DEADLINE_S) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


def rlpipe(args, cwd: Path, **kw) -> tuple[int, str, str]:
    return finish(start(args, cwd, **kw))


def wait_stopped(proc: subprocess.Popen) -> None:
    """Until ``proc`` is stopped (SIGSTOP from its fault point): its state in /proc says so."""
    deadline = time.monotonic() + DEADLINE_S
    while Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "T":
        assert proc.poll() is None, f"the run ended before its fault point: {proc.communicate()}"
        assert time.monotonic() < deadline, "the run did not reach its fault point"
        time.sleep(0.02)


@contextlib.contextmanager
def held(args, cwd: Path, fault: str, **kw):
    """A run held (SIGSTOP) at ``fault``; killed, group and all, if still there at the end."""
    proc = start(args, cwd, fault=f"{fault}:SIGSTOP", **kw)
    try:
        wait_stopped(proc)
        yield proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()


def resume_go_on(proc: subprocess.Popen) -> None:
    os.killpg(proc.pid, signal.SIGCONT)


def error_line(err: str) -> str:
    """The run's one line: stderr holds it alone, with no traceback."""
    assert "Traceback" not in err, err
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one line on stderr, got:\n{err}"
    return lines[0]


def metric_rows(run: Path) -> list[dict]:
    with (run / "metrics.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


def assert_whole_run(run: Path, iterations: int = N) -> None:
    """A finished run: every evaluation and log row once, in order, every row whole, no leftovers."""
    rows = metric_rows(run)
    assert all(None not in r.values() and None not in r for r in rows), rows
    assert [int(r["step"]) for r in rows if r["average_return"]] == list(range(0, iterations + 1, 100))
    assert [int(r["step"]) for r in rows if r["steps_per_s"]] == list(range(100, iterations + 1, 100))
    summary = json.loads((run / "summary.json").read_text())
    assert summary["iterations"] == iterations
    assert leftovers(run) == []


def leftovers(run: Path) -> list[str]:
    return sorted(str(p.relative_to(run)) for p in run.rglob(".*") if p.name not in (".mpl",))


def REFUSED(line: str) -> bool:  # noqa: N802 - read as a phrase
    return "Permission denied" in line or "Read-only file system" in line


@contextlib.contextmanager
def read_only(folder: Path):
    """``folder`` made read-only for every process while inside. Root writes through permissions, so
    as root the folder is bind-mounted read-only onto itself (skipped where mounting is not allowed)."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        try:
            yield
        finally:
            folder.chmod(0o755)
        return
    made = subprocess.run(["mount", "--bind", str(folder), str(folder)], capture_output=True)
    if made.returncode != 0:
        pytest.skip(f"cannot bind-mount here: {made.stderr.decode().strip()}")
    try:
        subprocess.run(["mount", "-o", "remount,bind,ro", str(folder)], check=True, capture_output=True)
        yield
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    cwd = tmp_path_factory.mktemp("trained")
    code, _, err = rlpipe(["train", "dqn", *TINY, "--no-progress", "--out", "run"], cwd)
    assert code == 0, err
    return cwd / "run"


def copy_of(trained: Path, dest: Path) -> Path:
    shutil.copytree(trained, dest, copy_function=shutil.copy2)
    return dest


# --- kill -9 inside a save -------------------------------------------------------------------------------


@pytest.mark.parametrize("point", ["checkpoint.written", "checkpoint.exchanged"])
@pytest.mark.slow
def test_kill_inside_a_checkpoint_overwrite_leaves_a_resumable_run(trained, tmp_path, point):
    """Resuming a run killed before its summary saves its last checkpoint again (an overwrite): killed before the new one
    is in, or after it is in and before the old one is removed, the run resumes, and the next start
    clears what the kill left (the temporary folder, a temporary export file)."""
    run = copy_of(trained, tmp_path / "run")
    # killed after its last checkpoint and before its summary: a resume owes the run's end again, and saves
    # that checkpoint again (a finished run, summary written, owes nothing and is left as it is)
    (run / "summary.json").unlink()
    code, _, err = rlpipe(["train", "dqn", "--resume", run, "--no-progress"], tmp_path, fault=f"{point}@{N}:SIGKILL")
    assert code == -signal.SIGKILL, f"not killed at {point}: exit {code}\n{err}"
    assert [p.name.split("-")[0] for p in (run / "checkpoints").glob(".tmp-*")] == [".tmp"], "the kill left no trace?"
    assert ckpt.latest_checkpoint(run / "checkpoints").name == f"step_{N:010d}"
    (run / "policy" / ".policy.pt2.k1lled_x.pt2").write_bytes(b"half an export")  # a kill inside an export

    code, out, err = rlpipe(["train", "dqn", "--resume", run, "--no-progress"], tmp_path)
    assert code == 0, err
    assert "AverageReturn" in out
    assert_whole_run(run)
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["latest", "step_0000000100", "step_0000000200"]


# --- killed before the first checkpoint ------------------------------------------------------------------


@pytest.fixture(scope="module")
def killed_while_starting(tmp_path_factory) -> Path:
    """A run killed inside its first save (iteration 0): config.json written, no checkpoint yet."""
    cwd = tmp_path_factory.mktemp("killed")
    code, _, err = rlpipe(["train", "dqn", *TINY, "--no-progress", "--out", "run"], cwd,
                          fault="checkpoint.write@0:SIGKILL")
    assert code == -signal.SIGKILL, err
    run = cwd / "run"
    assert (run / "config.json").exists() and not (run / "checkpoints" / "latest").exists()
    return run


@pytest.mark.parametrize("how", ["--resume", "--out"])
@pytest.mark.slow
def test_a_run_killed_before_its_first_checkpoint_resumes_or_restarts_in_place(killed_while_starting, tmp_path,
                                                                               how):
    run = copy_of(killed_while_starting, tmp_path / "run")
    args = ["train", "dqn", "--resume", run] if how == "--resume" else ["train", "dqn", *TINY, "--out", run]
    code, out, err = rlpipe([*args, "--no-progress"], tmp_path)
    assert code == 0, err
    said = error_line(err)
    assert said.startswith("rlpipe: ") and "before its first checkpoint" in said, said
    assert_whole_run(run)


# --- one writer per run directory ------------------------------------------------------------------------


@pytest.mark.slow
def test_a_second_writer_is_refused_naming_the_first_and_kill_9_leaves_no_stale_lock(tmp_path, monkeypatch, capsys):
    from rlpipe.scripts.cli import main

    run = tmp_path / "run"
    with held(["train", "dqn", *TINY, "--no-progress", "--out", run], tmp_path, "evaluate@100") as first:
        before = sorted(p.name for p in run.rglob("*"))
        monkeypatch.chdir(tmp_path)
        for argv in (["train", "dqn", "--resume", str(run)], ["train", "dqn", *TINY, "--out", str(run)]):
            capsys.readouterr()
            assert main([*argv, "--no-progress"]) == 2
            line = error_line(capsys.readouterr().err)
            assert f"pid {first.pid}" in line and "train dqn" in line and f"--out {run}" in line, line
        assert sorted(p.name for p in run.rglob("*")) == before, "the refused command wrote into the run"
        os.killpg(first.pid, signal.SIGKILL)  # no chance to clean up: the system drops its lock
        first.communicate()

    code, _, err = rlpipe(["train", "dqn", "--resume", run, "--no-progress"], tmp_path)
    assert code == 0, err
    assert_whole_run(run)


# --- refused writes: a full disk, a folder that turns read-only ------------------------------------------


@pytest.fixture
def tiny_disk(tmpfs):
    """A 32 MiB file system of its own (tmpfs), to fill."""
    return tmpfs("32m")


def fill(disk: Path) -> Path:
    filler = disk / "filler"
    with filler.open("wb") as fh:
        try:
            while True:
                fh.write(b"\0" * (1 << 20))
                fh.flush()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
    with contextlib.suppress(OSError):  # the last, partial block
        os.truncate(filler, filler.stat().st_size)
    return filler


@pytest.mark.slow
def test_a_full_disk_stops_the_run_with_one_line_and_loses_nothing(tiny_disk):
    run = tiny_disk / "run"
    with held(["train", "dqn", *TINY, "--no-progress", "--out", run], tiny_disk, "evaluate@100") as proc:
        kept = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
        filler = fill(tiny_disk)
        resume_go_on(proc)
        code, _, err = finish(proc)
    assert code == 2, err
    line = error_line(err)
    assert "No space left on device" in line and f"--resume {run}" in line, line
    assert "step_0000000000, is intact" in line, line
    for path, data in kept.items():  # nothing written before is lost or torn (metrics and events: appended to)
        assert path.read_bytes().startswith(data), path
    assert ckpt.latest_checkpoint(run / "checkpoints").name == "step_0000000000"
    assert not list(run.rglob(".tmp-*"))

    filler.unlink()
    code, _, err = rlpipe(["train", "dqn", "--resume", run, "--no-progress"], tiny_disk)
    assert code == 0, err
    assert_whole_run(run)


@pytest.mark.slow
def test_a_folder_turned_read_only_mid_run_saves_where_it_can(tmp_path):
    """The export folder turns read-only: the run stops with one line and a checkpoint of where it was
    (the checkpoints folder is still writable), and --resume goes on from there, losing nothing."""
    cwd, run = tmp_path, tmp_path / "run"
    # exported every 50 iterations: the folder is there when the run is held
    with held(["train", "dqn", *TINY, "policy_save_interval=50", "--no-progress", "--out", run], cwd,
              "evaluate@100") as proc:
        with read_only(run / "policy"):
            resume_go_on(proc)
            code, _, err = finish(proc)
    assert code == 2, err
    line = error_line(err)
    assert "/policy/" in line and REFUSED(line) and "saved a checkpoint at iteration 100" in line, line
    assert ckpt.latest_checkpoint(run / "checkpoints").name == "step_0000000100"

    code, _, err = rlpipe(["train", "dqn", "--resume", run, "--no-progress"], cwd)
    assert code == 0, err
    assert_whole_run(run)


@pytest.mark.slow
def test_ctrl_c_when_the_checkpoints_cannot_be_written_is_one_line(tmp_path):
    cwd, run = tmp_path, tmp_path / "run"
    with held(["train", "dqn", *TINY, "--no-progress", "--out", run], cwd, "evaluate@100") as proc:
        with read_only(run / "checkpoints"):
            os.killpg(proc.pid, signal.SIGINT)  # pressed while held: it lands when the run goes on
            resume_go_on(proc)
            code, _, err = finish(proc)
    assert code == 2, err
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert "Traceback" not in err and len(lines) == 2 and "stopping at the next safe point" in lines[0], err
    assert REFUSED(lines[1]) and "step_0000000000, is intact" in lines[1], lines[1]
    assert ckpt.latest_checkpoint(run / "checkpoints").name == "step_0000000000"
    assert not list((run / "checkpoints").glob(".tmp-*"))


@pytest.mark.parametrize("where", ["read-only-folder", "under-a-read-only-folder"])
@pytest.mark.slow
def test_an_unwritable_out_is_one_line_and_leaves_nothing(tmp_path, where):
    cwd = tmp_path
    locked = cwd / "locked"
    locked.mkdir()
    out = locked if where == "read-only-folder" else locked / "run"
    before = sorted(cwd.rglob("*"))
    with read_only(locked):
        code, _, err = rlpipe(["train", "dqn", *TINY, "--no-progress", "--out", out], cwd)
    assert code == 2, err
    line = error_line(err)
    assert line.startswith("rlpipe: error:") and str(out) in line and REFUSED(line), line
    assert sorted(cwd.rglob("*")) == before


# --- resuming: what the run's figures and files say --------------------------------------------------------


def files_of(run: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(run)): (p.stat().st_mtime_ns, p.stat().st_size) for p in run.rglob("*") if p.is_file()}


def test_a_finished_run_resumed_with_nothing_owed_changes_nothing_and_says_so(trained, tmp_path, monkeypatch, capsys):
    """It once exited 0 having rewritten summary.json ("wall time 1.3 s" of a 9.1 s run), the page and the checkpoint."""
    from rlpipe.scripts.cli import main

    run = copy_of(trained, tmp_path / "run")
    before = files_of(run)
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    code = main(["train", "dqn", "--resume", "run", "--no-progress"])
    out, err = capsys.readouterr()
    assert code == 0
    assert error_line(err).startswith(f"rlpipe: run finished all {N} iterations and owes nothing: nothing changed")
    assert files_of(run) == before
    summary = json.loads((run / "summary.json").read_text())
    assert f"in {summary['wall_time_s']:.0f} s" in out  # the run's own figures, as its first stretch wrote them


def facts_of(page: str) -> dict[str, str]:
    """The report page's facts table, name -> text."""
    import html
    import re

    table = page.split('<table id="facts">', 1)[1].split("</table>", 1)[0]
    return {html.unescape(k): html.unescape(v) for k, v in
            re.findall(r'<th class="text">(.*?)</th><td class="text">(.*?)</td>', table, re.S)}


@pytest.mark.slow
def test_a_stopped_runs_page_and_figures_tell_the_truth_through_its_resume(tmp_path):
    """Once: the page stayed at "at iteration 0" with empty losses until the next evaluation, said nothing of a
    stopped run, and offered `rlpipe video RUN` before there was a policy to film; after a resume, summary.json's
    wall time and speeds and metrics.csv's wall_time covered only the stretch since the resume while saying
    "whole run"; and nothing said where the run resumed."""
    from rlpipe.pipelines.analysis.report_pages import write_run_report

    args = ["train", "dqn", *TINY, "eval_interval=0", "log_interval=50", "policy_save_interval=1000",
            "--no-progress", "--out", "run"]
    run = tmp_path / "run"
    with held(args, tmp_path, "collected@50") as proc:
        page = (run / "report.html").read_text()
        assert facts_of(page)["status"] == f"at iteration 50 of {N}"  # refreshed by the first log row
        assert '<table id="log">' in page  # the losses and speeds so far, with no evaluation since iteration 0
        assert "no policy to film" in page and "every 1,000 iterations" in page  # not exported yet: said so
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C, while held: it lands when the run goes on
        resume_go_on(proc)
        code, _, err = finish(proc)
    assert code == 130, err
    facts = facts_of((run / "report.html").read_text())
    assert facts["status"].startswith("stopped at iteration ") and "its last checkpoint is at iteration" in facts["status"]
    assert facts["to continue it"] == f"rlpipe train dqn --resume {run.resolve()}"
    write_run_report(run)  # `rlpipe report run` later, from the files alone: no process writes the run
    assert facts_of((run / "report.html").read_text())["to continue it"] == f"rlpipe train dqn --resume {run.resolve()}"

    saved = ckpt.load_checkpoint(ckpt.latest_checkpoint(run / "checkpoints"), "dqn", "CartPole-v0")["counters"]
    stopped_at = saved["iteration"]
    assert 0 < stopped_at < N and saved["wall_time_s"] >= max(float(r["wall_time"]) for r in metric_rows(run)) > 0
    assert 0 < saved["train_time_s"] < saved["wall_time_s"]
    code, out, err = rlpipe(["train", "dqn", "--resume", "run", "--no-progress"], tmp_path)
    assert code == 0, err
    assert out.splitlines()[0].startswith(f"resumed at iteration {stopped_at} of {N} (")
    rows = metric_rows(run)
    assert [int(r["step"]) for r in rows if r["average_return"]] == [0, N]
    assert [int(r["step"]) for r in rows if r["steps_per_s"]] == list(range(50, N + 1, 50))
    resumed = [float(r["wall_time"]) for r in rows if int(r["step"]) > stopped_at]
    assert resumed and min(resumed) >= saved["wall_time_s"]  # the clock went on from where the checkpoint left it
    summary = json.loads((run / "summary.json").read_text())
    assert summary["wall_time_s"] >= max(resumed) and summary["train_time_s"] > saved["train_time_s"]
    assert summary["env_steps_per_s"] == pytest.approx(summary["frames"] / summary["train_time_s"])
    page = (run / "report.html").read_text()
    assert facts_of(page)["status"] == "finished" and "to continue it" not in facts_of(page)
    assert "no policy to film" not in page and "makes one" in page  # exported at the end: `rlpipe video run` works


def test_live_report_false_writes_the_page_at_the_end_only(tmp_path):
    """The sized presets' setting: no page or plot from the log rows or evaluations (the first page costs 1-2 s of a
    10-s run), both at the end."""
    args = ["train", "dqn", *TINY, "eval_interval=50", "initial_eval=false", "live_report=false", "log_interval=50",
            "--no-progress", "--out", "run"]
    run = tmp_path / "run"
    with held(args, tmp_path, "collected@150") as proc:
        rows = metric_rows(run)
        assert [int(r["step"]) for r in rows if r["steps_per_s"]][:2] == [50, 100]  # log rows were written
        assert [int(r["step"]) for r in rows if r["average_return"]][:2] == [50, 100]  # and evaluations
        assert not (run / "report.html").exists() and not (run / "returns.png").exists()
        resume_go_on(proc)
        code, _, err = finish(proc)
    assert code == 0, err
    assert facts_of((run / "report.html").read_text())["status"] == "finished"
    assert (run / "returns.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_page_and_plot_follow_evaluations_at_a_bounded_cost(trained, tmp_path):
    """The DQN tutorial evaluates 21 times in a ~30-s run: drawing at each one took 14 s of it. The first evaluation
    draws at once; one soon after waits (the page's bound); the run's end draws what came since."""
    from rlpipe.pipelines.training.live_report import ReportPage

    run = copy_of(trained, tmp_path / "run")
    (run / "returns.png").unlink()
    evaluations = [{"step": 0, "average_return": 10.0, "average_episode_length": 10.0}]
    page = ReportPage(run, evaluations, title="dqn on CartPole-v0")
    assert page.evaluated() and (run / "returns.png").exists() and (run / "report.html").exists()
    first = (run / "returns.png").read_bytes()
    evaluations.append({"step": 100, "average_return": 200.0, "average_episode_length": 200.0})
    assert not page.evaluated() and (run / "returns.png").read_bytes() == first  # within the bound: not drawn
    page.write(running=False)
    assert (run / "returns.png").read_bytes() != first  # the end: both points
