"""Checkpoints and resume: atomic saves, weights-only loads, bad checkpoints refused, Ctrl-C, --resume.

A run trained once in-process (module fixture) is copied for every case that damages or resumes it.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import json
import os
import pickle
import random
import shutil
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import torch

from rlpipe.pipelines import InputError
from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.dqn import DQN, preset

BASE = ["initial_collect_steps=100", "eval_interval=100", "num_eval_episodes=2", "log_interval=100",
        "checkpoint_interval=100", "policy_save_interval=100"]
N = 200  # iterations of the saved run
RLPIPE = [sys.executable, "-m", "rlpipe.scripts.cli"]


def cfg_with(*extra: str):
    return apply_overrides(preset("dqn"), BASE + [f"num_iterations={N}"] + list(extra))


def rlpipe(*args, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(RLPIPE + [str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=timeout)


def snapshot(folder: Path) -> dict[str, tuple]:
    """Every file and folder under ``folder`` with its size, mtime and content hash."""
    state = {}
    for path in sorted(folder.rglob("*")):
        rel = str(path.relative_to(folder))
        if path.is_dir():
            state[rel] = ("dir", path.stat().st_mtime_ns)
        else:
            st = path.stat()
            state[rel] = (st.st_size, st.st_mtime_ns, hashlib.sha256(path.read_bytes()).hexdigest())
    return state


def assert_one_line_error(proc: subprocess.CompletedProcess, *words: str) -> str:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, f"exit {proc.returncode}; stderr:\n{proc.stderr}"
    assert len(lines) == 1, f"expected one line on stderr, got:\n{proc.stderr}"
    assert lines[0].startswith("rlpipe: error:"), lines[0]
    for word in words:
        assert word in lines[0], f"{word!r} not in {lines[0]!r}"
    return lines[0]


def metric_rows(run: Path) -> list[dict]:
    with (run / "metrics.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


def assert_no_duplicated_steps(rows: list[dict]) -> None:
    evals = [int(r["step"]) for r in rows if r["average_return"]]
    logs = [int(r["step"]) for r in rows if r["loss_loss"]]
    assert len(evals) == len(set(evals)), f"duplicated evaluation steps: {evals}"
    assert len(logs) == len(set(logs)), f"duplicated log steps: {logs}"
    steps = [int(r["step"]) for r in rows]
    assert steps == sorted(steps), steps


@pytest.fixture(scope="module")
def saved_run(tmp_path_factory):
    """A finished run of N iterations with checkpoints every 100, and its pipeline."""
    run = tmp_path_factory.mktemp("saved") / "run"
    pipeline = DQN(cfg_with())
    result = pipeline.train(run, progress=False)
    return run, pipeline, result


def copy_run(saved_run, dest: Path) -> Path:
    shutil.copytree(saved_run[0], dest, copy_function=shutil.copy2)
    return dest


# --- writing and reading checkpoints -------------------------------------------------------------


def test_checkpoints_keep_counters_and_the_replay_buffer(saved_run):
    run, pipeline, _ = saved_run
    latest = ckpt.latest_checkpoint(run / "checkpoints")
    assert latest.name == f"step_{N:010d}"
    fresh = DQN(cfg_with())
    assert len(fresh.replay_buffer) == 0
    state = ckpt.load_checkpoint(latest, "dqn", "CartPole-v0")
    assert state["counters"]["frames"] == 100 + N and state["counters"]["updates"] == N
    assert state["counters"]["iteration"] == N
    fresh.load_state_dict(state)
    assert len(fresh.replay_buffer) == len(pipeline.replay_buffer) == 100 + N
    n = len(pipeline.replay_buffer)
    torch.testing.assert_close(fresh.replay_buffer[:n]["observation"], pipeline.replay_buffer[:n]["observation"])
    torch.testing.assert_close(fresh.replay_buffer[:n]["action"], pipeline.replay_buffer[:n]["action"])
    fresh.load_state_dict(state)
    for key, value in pipeline.loss_module.state_dict().items():
        torch.testing.assert_close(fresh.loss_module.state_dict()[key], value)


def test_the_buffer_keeps_what_the_loss_reads_unless_asked_for_all(saved_run, tmp_path):
    run, pipeline, _ = saved_run
    assert set(pipeline.replay_buffer[:].keys(True, True)) == set(pipeline.loss_module.in_keys)
    # every key the collector returns, on request ...
    full = DQN(cfg_with("num_iterations=10", "replay_all_keys=true"))
    full.train(tmp_path / "full", progress=False)
    stored = set(full.replay_buffer[:].keys(True, True))
    assert {("collector", "traj_ids"), "step_count"} <= stored and set(full.loss_module.in_keys) < stored
    # ... and a run that stores fewer keys resumes from such a checkpoint, and trains on
    lean = DQN(cfg_with("num_iterations=20"))
    lean.load_state_dict(ckpt.load_checkpoint(ckpt.latest_checkpoint(tmp_path / "full" / "checkpoints"),
                                              "dqn", "CartPole-v0"))
    assert set(lean.replay_buffer[:].keys(True, True)) == set(lean.loss_module.in_keys)
    result = lean.train(tmp_path / "full", resume=True, progress=False)
    assert result.summary["iterations"] == 20 and len(lean.replay_buffer) == 100 + 20


def test_leftover_tmp_folder_from_a_crash_does_not_break_latest(saved_run, tmp_path):
    run = copy_run(saved_run, tmp_path / "run")
    folder = run / "checkpoints"
    before = ckpt.latest_checkpoint(folder)
    # a crash mid-save leaves a half-written temporary folder behind
    junk = folder / ".tmp-crashed"
    junk.mkdir()
    (junk / "state.pt").write_bytes(b"half a checkpoint")
    assert ckpt.latest_checkpoint(folder) == before
    state = ckpt.load_checkpoint(before, "dqn", "CartPole-v0")
    assert state["step"] == N
    # and the next save still works and moves `latest`
    path = ckpt.save_checkpoint(folder, N + 1, {"algo": "dqn", "env": "CartPole-v0", "x": torch.ones(2)})
    assert ckpt.latest_checkpoint(folder) == path
    assert ckpt.load_checkpoint(path, "dqn", "CartPole-v0")["step"] == N + 1


def test_a_save_that_fails_midway_leaves_the_previous_checkpoint(saved_run, tmp_path):
    run = copy_run(saved_run, tmp_path / "run")
    folder = run / "checkpoints"
    before = ckpt.latest_checkpoint(folder)
    listing = sorted(p.name for p in folder.iterdir())
    with pytest.raises((pickle.PicklingError, AttributeError)):  # AttributeError: a local object
        # a lambda cannot be pickled: torch.save fails after the temporary folder was made
        ckpt.save_checkpoint(folder, N + 1, {"algo": "dqn", "env": "CartPole-v0", "bad": lambda: 0})
    assert ckpt.latest_checkpoint(folder) == before
    assert sorted(p.name for p in folder.iterdir()) == listing, "the failed save left something behind"
    assert ckpt.load_checkpoint(before, "dqn", "CartPole-v0")["step"] == N


class _RunsCode:
    """A pickle payload that would create a file if the checkpoint were loaded with full pickle."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_loading_never_runs_code_from_a_checkpoint(saved_run, tmp_path):
    marker = tmp_path / "code-ran"
    folder = tmp_path / "ck"
    folder.mkdir()
    torch.save({"format": ckpt.FORMAT, "algo": "dqn", "env": "CartPole-v0", "x": _RunsCode(marker)}, folder / "state.pt")
    with pytest.raises(InputError, match="state.pt"):
        ckpt.load_checkpoint(folder, "dqn", "CartPole-v0")
    assert not marker.exists(), "loading a checkpoint ran code from it"


def test_checkpoint_is_one_weights_only_file(saved_run):
    # TorchRL's ReplayBuffer.dumps() writes a pickle that loads() would unpickle: the buffer's
    # transitions live in state.pt instead, which torch reads with weights_only=True.
    checkpoint = ckpt.latest_checkpoint(saved_run[0] / "checkpoints")
    assert sorted(p.name for p in checkpoint.iterdir()) == ["state.pt"]
    state = torch.load(checkpoint / "state.pt", weights_only=True)
    assert state["replay_buffer"]["len"] == 100 + N


def test_load_refuses_another_algo_or_env(saved_run):
    latest = ckpt.latest_checkpoint(saved_run[0] / "checkpoints")
    with pytest.raises(InputError, match="td3"):
        ckpt.load_checkpoint(latest, "td3", "CartPole-v0")
    with pytest.raises(InputError, match="CartPole-v1"):
        ckpt.load_checkpoint(latest, "dqn", "CartPole-v1")


def test_any_bytes_in_place_of_a_checkpoint_are_an_input_error(tmp_path):
    # torch.load raises many kinds of exception on arbitrary bytes (IndexError, KeyError, ...);
    # each must become the one-line error. 200 byte strings, seeded: the same ones every run.
    folder = tmp_path / "step_0000000001"
    folder.mkdir()
    rng = random.Random(1)
    for i in range(200):
        data = rng.randbytes(rng.randrange(1, 5000))
        if i % 4 == 0:
            data = b"PK\x03\x04" + data  # a zip header: torch reads it as an archive
        elif i % 4 == 1:
            data = b"\x80\x02" + data  # a pickle protocol header: the legacy format's unpickler
        (folder / "state.pt").write_bytes(data)
        with pytest.raises(InputError, match="corrupt or not an rlpipe checkpoint"):
            ckpt.load_checkpoint(folder, "dqn", "CartPole-v0")


def test_missing_checkpoint_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="no checkpoint"):
        ckpt.latest_checkpoint(tmp_path)


# --- resume ----------------------------------------------------------------------------------------


def test_resume_continues_counters_buffer_and_metrics(saved_run, tmp_path):
    run = copy_run(saved_run, tmp_path / "run")
    rows_before = metric_rows(run)
    pipeline = DQN(cfg_with(f"num_iterations={2 * N}"))
    result = pipeline.train(run, resume=True, progress=False)
    s = result.summary
    assert (s["iterations"], s["frames"], s["updates"]) == (2 * N, 100 + 2 * N, 2 * N)
    # the saved transitions came back, and the new ones were added to them
    assert len(pipeline.replay_buffer) == 100 + 2 * N
    old = saved_run[1].replay_buffer
    torch.testing.assert_close(pipeline.replay_buffer[: len(old)]["observation"], old[: len(old)]["observation"])
    rows = metric_rows(run)
    assert rows[: len(rows_before)] == rows_before, "rows of the first part were changed"
    new = rows[len(rows_before):]
    assert new and all(int(r["step"]) > N for r in new), [r["step"] for r in new]
    assert_no_duplicated_steps(rows)
    assert [int(r["step"]) for r in rows if r["average_return"]] == [0, 100, 200, 300, 400]
    last = rows[-1]
    assert (int(last["step"]), int(last["frames"]), int(last["updates"])) == (2 * N, 100 + 2 * N, 2 * N)
    assert ckpt.latest_checkpoint(run / "checkpoints").name == f"step_{2 * N:010d}"


def test_resuming_a_finished_run_adds_no_duplicated_rows(saved_run, tmp_path):
    run = copy_run(saved_run, tmp_path / "run")
    DQN(cfg_with()).train(run, resume=True, progress=False)
    assert_no_duplicated_steps(metric_rows(run))


class _InterruptedDQN(DQN):
    """Gets a Ctrl-C (SIGINT to this process) in the middle of a block of updates."""

    at = 125

    def update(self, batch, update_index):
        self.calls = getattr(self, "calls", 0) + 1
        if self.calls == self.at:
            os.kill(os.getpid(), signal.SIGINT)
        return super().update(batch, update_index)


def test_ctrl_c_during_updates_loses_no_updates(tmp_path):
    cfg = apply_overrides(preset("dqn"), ["initial_collect_steps=100", "num_iterations=300", "eval_interval=0",
                                          "num_eval_episodes=1", "checkpoint_interval=100"])
    with pytest.raises(KeyboardInterrupt):
        _InterruptedDQN(cfg).train(tmp_path / "run", progress=False)
    # saved where it stopped: after the 125th update, within the block of iteration 150
    state = ckpt.load_checkpoint(ckpt.latest_checkpoint(tmp_path / "run" / "checkpoints"), "dqn", "CartPole-v0")
    assert state["counters"]["updates"] == 125 and state["counters"]["iteration"] == 150, state["counters"]
    result = DQN(cfg).train(tmp_path / "run", resume=True, progress=False)
    assert result.summary["iterations"] == 300
    assert result.summary["updates"] == 300


def test_resume_with_changed_keys_records_them_in_config_json(saved_run, tmp_path):
    run = copy_run(saved_run, tmp_path / "run")
    DQN(cfg_with(f"num_iterations={2 * N}")).train(run, resume=True, progress=False)
    saved = json.loads((run / "config.json").read_text())
    assert saved["config"]["num_iterations"] == 2 * N


class _InterruptedAtStart(DQN):
    """Gets a Ctrl-C while the collector starts (seconds with collector.workers>1)."""

    def make_backend(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        return super().make_backend(*args, **kwargs)


def test_ctrl_c_before_the_first_checkpoint_can_be_resumed(tmp_path):
    cfg = apply_overrides(preset("dqn"), ["initial_collect_steps=100", "num_iterations=100", "eval_interval=0",
                                          "num_eval_episodes=1"])
    with pytest.raises(KeyboardInterrupt):
        _InterruptedAtStart(cfg).train(tmp_path / "run", progress=False)
    result = DQN(cfg).train(tmp_path / "run", resume=True, progress=False)
    assert result.summary["iterations"] == 100


def test_cli_resume_continues_the_run(saved_run, tmp_path):
    run = copy_run(saved_run, tmp_path / "run")
    # overrides before the options, as `rlpipe train PRESET [key=value ...] [--resume DIR]` documents
    proc = rlpipe("train", "dqn", f"num_iterations={2 * N}", "--resume", run, "--no-progress", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "AverageReturn" in proc.stdout
    summary = json.loads((run / "summary.json").read_text())
    assert (summary["iterations"], summary["frames"], summary["updates"]) == (2 * N, 100 + 2 * N, 2 * N)
    rows = metric_rows(run)
    assert_no_duplicated_steps(rows)
    assert max(int(r["step"]) for r in rows) == 2 * N


# --- bad checkpoints via `rlpipe train dqn --resume RUN` -----------------------------------------


def _state_of(run: Path) -> Path:
    return ckpt.latest_checkpoint(run / "checkpoints") / "state.pt"


def _every_state(run: Path) -> list[Path]:
    return [path / "state.pt" for path in ckpt.checkpoint_steps(run / "checkpoints").values()]


def _garbage(run: Path, marker: Path):
    for path in _every_state(run):  # one damaged checkpoint is skipped for the one before
        path.write_bytes(random.Random(0).randbytes(4096))


def _truncated(run: Path, marker: Path):
    for path in _every_state(run):
        path.write_bytes(path.read_bytes()[:1000])


def _foreign_dict(run: Path, marker: Path):
    torch.save({"model": {"weight": torch.zeros(3)}, "step": 5}, _state_of(run))


def _pickled_class(run: Path, marker: Path):
    torch.save({"format": ckpt.FORMAT, "algo": "dqn", "env": "CartPole-v0", "x": _RunsCode(marker)}, _state_of(run))


def _other_algo(run: Path, marker: Path):
    path = _state_of(run)
    state = torch.load(path, weights_only=True)
    state["algo"] = "sac"
    torch.save(state, path)


def _other_env(run: Path, marker: Path):
    path = _state_of(run)
    state = torch.load(path, weights_only=True)
    state["env"] = "Acrobot-v1"
    torch.save(state, path)


def _no_checkpoints(run: Path, marker: Path):
    shutil.rmtree(run / "checkpoints")


def _latest_names_a_parent(run: Path, marker: Path):
    (run / "checkpoints" / "latest").write_text("../../..\n")


def _latest_names_an_absolute_path(run: Path, marker: Path):
    (run / "checkpoints" / "latest").write_text(f"{run.parent}\n")


def _latest_is_a_link_outside(run: Path, marker: Path):
    outside = run.parent / "elsewhere"
    outside.write_text("step_0000000200\n")
    (run / "checkpoints" / "latest").unlink()
    (run / "checkpoints" / "latest").symlink_to(outside)


def _format_marker_only(run: Path, marker: Path):
    torch.save({"format": ckpt.FORMAT, "algo": "dqn", "env": "CartPole-v0", "step": N}, _state_of(run))


def _no_change(run: Path, marker: Path):
    pass


BAD_RESUMES = {
    # name: (damage, extra overrides, words the one-line error names)
    "garbage-bytes": (_garbage, [], ["no whole checkpoint", "step_0000000100", "step_0000000200"]),
    "truncated-file": (_truncated, [], ["no whole checkpoint", "state.pt"]),
    "foreign-dict": (_foreign_dict, [], ["not an rlpipe checkpoint"]),
    "pickled-class": (_pickled_class, [], ["state.pt"]),
    "other-algo": (_other_algo, [], ["sac", "dqn"]),
    "other-env": (_other_env, [], ["Acrobot-v1", "CartPole-v0"]),
    "env-override": (_no_change, ["env=CartPole-v1"], ["CartPole-v0", "CartPole-v1"]),
    "no-checkpoints": (_no_checkpoints, [], ["no checkpoint"]),
    "latest-names-a-parent": (_latest_names_a_parent, [], ["latest", "'../../..'", "step_NNNNNNNNNN"]),
    "latest-names-an-absolute-path": (_latest_names_an_absolute_path, [], ["latest", "step_NNNNNNNNNN"]),
    "latest-is-a-link-outside": (_latest_is_a_link_outside, [], ["latest", "symbolic link"]),
    "network-override": (_no_change, ["fc_layer_params=[50]"], ["fc_layer_params"]),
    "marker-only": (_format_marker_only, [], ["state.pt"]),
}



def _prepare(saved_run, root: Path, name: str) -> tuple[Path, Path]:
    damage = BAD_RESUMES[name][0]
    cwd = root / name
    cwd.mkdir()
    run = copy_run(saved_run, cwd / "run")
    marker = cwd / "code-ran"
    damage(run, marker)
    return cwd, marker



@pytest.mark.parametrize("name", list(BAD_RESUMES))
def test_bad_checkpoint_is_one_line_exit_2_and_touches_nothing(saved_run, tmp_path, monkeypatch, capsys, name):
    """`rlpipe train dqn [key=value] --resume RUN` through the CLI's main(), in this process (fast)."""
    from rlpipe.scripts.cli import main

    cwd, marker = _prepare(saved_run, tmp_path, name)
    monkeypatch.chdir(cwd)
    before = snapshot(cwd)
    capsys.readouterr()
    code = main(["train", "dqn", *BAD_RESUMES[name][1], "--resume", str(cwd / "run"), "--no-progress"])
    err = capsys.readouterr().err
    assert not marker.exists(), "resuming ran code stored in the checkpoint"
    assert_one_line_error(subprocess.CompletedProcess([], code, "", err), *BAD_RESUMES[name][2])
    assert snapshot(cwd) == before, "the run directory was modified"


SUBPROCESS_CASES = ["garbage-bytes", "pickled-class", "other-env"]


@pytest.fixture(scope="module")
def bad_resume_processes(saved_run, tmp_path_factory):
    """A few bad --resume cases as real processes, two at a time."""
    root = tmp_path_factory.mktemp("bad-resumes")

    def one(name):
        cwd, marker = _prepare(saved_run, root, name)
        before = snapshot(cwd)
        proc = rlpipe("train", "dqn", *BAD_RESUMES[name][1], "--resume", "run", "--no-progress", cwd=cwd)
        return name, (proc, before, snapshot(cwd), marker.exists())

    with ThreadPoolExecutor(max_workers=2) as pool:
        return dict(pool.map(one, SUBPROCESS_CASES))


@pytest.mark.parametrize("name", SUBPROCESS_CASES)
def test_bad_checkpoint_in_a_real_process(bad_resume_processes, name):
    proc, before, after, code_ran = bad_resume_processes[name]
    assert not code_ran, "resuming ran code stored in the checkpoint"
    assert_one_line_error(proc, *BAD_RESUMES[name][2])
    assert after == before, "the run directory was modified"


# --- Ctrl-C ------------------------------------------------------------------------------------------


def _session_processes(sid: int) -> list[int]:
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[3]) == sid and fields[0] != "Z":  # field 6 of stat: session id
            pids.append(int(entry.name))
    return pids


def _wait_stopped(proc: subprocess.Popen) -> None:
    """Until ``proc`` is stopped (SIGSTOP from its fault point): its state in /proc says so."""
    deadline = time.monotonic() + 240  # generous: the machine is shared; the wait is for the event
    while Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "T":
        assert proc.poll() is None, f"the run ended before its fault point: {proc.communicate()}"
        assert time.monotonic() < deadline, "the run did not reach its fault point"
        time.sleep(0.02)


def _held(args: list[str], run: Path, at: int, command: list[str] = RLPIPE, **popen) -> subprocess.Popen:
    """``rlpipe ARGS --out RUN`` in its own process group, held (SIGSTOP to the group, from rlpipe's
    fault hook) once the block of iteration ``at`` is collected."""
    proc = subprocess.Popen([*command, *args, "--out", str(run)], cwd=run.parent, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env={**os.environ, "RLPIPE_FAULT": f"collected@{at}:SIGSTOP"}, **popen)
    try:
        _wait_stopped(proc)
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    return proc


# Ctrl-C to a run with collector processes, its checkpoint where it stopped, no child left and --resume to the end:
# tests/test_collectors.py's `interrupted` run (twice, with the evaluator's process too) and
# tests/test_resume_exact.py (equal to the uninterrupted run); the `rlpipe` entry point: tests/test_cli.py.


def _logged_past(run: Path, step: int) -> bool:
    try:
        return any(int(r["step"]) >= step for r in metric_rows(run))
    except (OSError, ValueError, TypeError):  # not written yet, or a line half-written
        return False


@contextlib.contextmanager
def _run_logged_past(args: list[str], run: Path, step: int, **popen):
    """``rlpipe ARGS --out RUN`` in its own process group, handed over once it has logged past
    ``step``; killed (group and all) if still running at exit."""
    proc = subprocess.Popen([*RLPIPE, *args, "--out", str(run)], cwd=run.parent, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, **popen)
    try:
        deadline = time.monotonic() + 180
        while not _logged_past(run, step):
            assert proc.poll() is None, f"training ended before step {step}: {proc.communicate()}"
            assert time.monotonic() < deadline, f"no row past step {step} within 180 s"
            time.sleep(0.01)
        yield proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


@pytest.mark.slow
def test_resume_after_a_kill_has_every_evaluation_once(tmp_path):
    """kill -9 (no chance to save): --resume continues from the last periodic checkpoint, and the
    rows written after it are replaced, not repeated."""
    run = tmp_path / "run"
    args = ["train", "dqn", "num_iterations=600", "initial_collect_steps=100", "eval_interval=100",
            "num_eval_episodes=1", "log_interval=50", "checkpoint_interval=100", "policy_save_interval=100",
            "--no-progress"]
    with _run_logged_past(args, run, 350) as proc:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=60)
    assert not (run / "summary.json").exists()
    saved = ckpt.load_checkpoint(ckpt.latest_checkpoint(run / "checkpoints"), "dqn", "CartPole-v0")["counters"]
    assert 0 < saved["iteration"] < 600
    out = rlpipe("train", "dqn", "--resume", run, "--no-progress", cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    rows = metric_rows(run)
    assert_no_duplicated_steps(rows)
    assert [int(r["step"]) for r in rows if r["average_return"]] == list(range(0, 601, 100))
    assert [int(r["step"]) for r in rows if r["steps_per_s"]] == list(range(50, 601, 50))


def test_a_run_started_immune_to_ctrl_c_stays_so(tmp_path):
    """Started with SIGINT ignored (nohup, a background job), a run ignores it, as Python does."""
    run = tmp_path / "run"
    args = ["train", "dqn", "num_iterations=300", "initial_collect_steps=100", "eval_interval=100",
            "num_eval_episodes=1", "log_interval=100", "checkpoint_interval=100", "--no-progress"]
    # held mid-run (after the block of iteration 200), so the Ctrl-C surely finds it running
    proc = _held(args, run, 200, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        os.killpg(proc.pid, signal.SIGINT)
        os.killpg(proc.pid, signal.SIGCONT)
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, err[-3000:]
    assert json.loads((run / "summary.json").read_text())["iterations"] == 300


# --- crash-safe saves ----------------------------------------------------------------------------------


def _small_state(x: float) -> dict:
    return {"algo": "dqn", "env": "CartPole-v0", "x": torch.full((3,), x)}


def _x_of(path: Path) -> float:
    return float(ckpt.load_checkpoint(path, "dqn", "CartPole-v0")["x"][0])


@pytest.mark.unit
def test_every_instant_of_an_overwrite_leaves_latest_naming_a_whole_checkpoint(tmp_path, monkeypatch):
    """A checkpoint saved again at the same step (a Ctrl-C after the periodic save, a finished run
    resumed) replaces the old one: at each point inside the save where a kill could land, the
    checkpoint a resume would take is whole, the old one or the new one."""
    folder = tmp_path / "checkpoints"
    ckpt.save_checkpoint(folder, 5, _small_state(1.0))
    seen = {}

    def at(name, step):
        path = ckpt.latest_checkpoint(folder)
        seen[name] = (path.name, _x_of(path))

    monkeypatch.setattr(ckpt, "fault_point", at)
    ckpt.save_checkpoint(folder, 5, _small_state(2.0))
    assert set(seen) >= {"checkpoint.write", "checkpoint.written", "checkpoint.exchanged", "checkpoint.latest"}
    assert seen["checkpoint.written"] == ("step_0000000005", 1.0)  # the new one is whole, not in yet
    assert seen["checkpoint.exchanged"] == ("step_0000000005", 2.0)  # in; the old one not yet removed
    assert _x_of(ckpt.latest_checkpoint(folder)) == 2.0
    assert sorted(p.name for p in folder.iterdir()) == ["latest", "step_0000000005"]


@pytest.mark.unit
def test_without_an_atomic_exchange_a_checkpoint_set_aside_comes_back(tmp_path, monkeypatch):
    """Where the system has no atomic exchange, the old checkpoint steps aside for the new one; killed
    in between, the next start puts it back."""
    folder = tmp_path / "checkpoints"
    ckpt.save_checkpoint(folder, 5, _small_state(1.0))
    monkeypatch.setattr(ckpt, "_exchange", lambda a, b: False)  # as on a system without renameat2

    class Killed(BaseException):
        pass

    def kill_at(name, step):
        if name == "checkpoint.aside":
            raise Killed

    monkeypatch.setattr(ckpt, "fault_point", kill_at)
    with pytest.raises(Killed):
        ckpt.save_checkpoint(folder, 5, _small_state(2.0))
    assert not (folder / "step_0000000005").exists()
    ckpt.remove_leftovers(folder)
    assert _x_of(ckpt.latest_checkpoint(folder)) == 1.0
    assert sorted(p.name for p in folder.iterdir()) == ["latest", "step_0000000005"]
    monkeypatch.setattr(ckpt, "fault_point", lambda name, step: None)
    ckpt.save_checkpoint(folder, 5, _small_state(2.0))
    assert _x_of(ckpt.latest_checkpoint(folder)) == 2.0


@pytest.mark.unit
def test_a_full_disk_inside_a_save_is_one_error_and_keeps_the_previous(tmp_path, monkeypatch):
    from rlpipe.pipelines.artifacts.files import FileWriteError
    from rlpipe.pipelines.system import faults

    folder = tmp_path / "checkpoints"
    ckpt.save_checkpoint(folder, 5, _small_state(1.0))
    monkeypatch.setattr(faults, "_FAULTS", ["checkpoint.write@6:ENOSPC"])
    with pytest.raises(FileWriteError, match="No space left on device") as raised:
        ckpt.save_checkpoint(folder, 6, _small_state(2.0))
    assert isinstance(raised.value, InputError) and len(str(raised.value).splitlines()) == 1
    assert ckpt.latest_checkpoint(folder).name == "step_0000000005"
    assert sorted(p.name for p in folder.iterdir()) == ["latest", "step_0000000005"]


@pytest.mark.unit
@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_checkpoint_folders_get_the_permissions_of_the_run_directory(tmp_path, umask):
    before = os.umask(umask)
    try:
        run = tmp_path / "run"
        run.mkdir()
        path = ckpt.save_checkpoint(run / "checkpoints", 1, _small_state(1.0))
    finally:
        os.umask(before)
    mode = run.stat().st_mode & 0o777
    assert mode == 0o777 & ~umask
    assert (run / "checkpoints").stat().st_mode & 0o777 == mode
    assert path.stat().st_mode & 0o777 == mode  # was 0700 (mkdtemp's)
    assert (path / "state.pt").stat().st_mode & 0o777 == 0o666 & ~umask


@pytest.mark.unit
def test_checkpoint_keep_prunes_the_oldest_once_a_new_one_is_whole(tmp_path):
    folder = tmp_path / "checkpoints"
    for keep, expected in ((2, [3, 4]), (1, [4]), (3, [2, 3, 4]), (0, [0, 1, 2, 3, 4])):
        shutil.rmtree(folder, ignore_errors=True)
        for step in range(5):
            ckpt.save_checkpoint(folder, step, _small_state(step), keep=keep)
        assert list(ckpt.checkpoint_steps(folder)) == expected, keep
    # a run resumed from an older checkpoint (the newer one damaged) drops the newer ones it abandons
    ckpt.save_checkpoint(folder, 2, _small_state(9.0), keep=2)
    assert list(ckpt.checkpoint_steps(folder)) == [1, 2]


def test_checkpoint_keep_in_a_run(tmp_path):
    cfg = apply_overrides(preset("dqn"), ["initial_collect_steps=100", "num_iterations=200", "eval_interval=0",
                                          "num_eval_episodes=1", "checkpoint_interval=50", "checkpoint_keep=0"])
    DQN(cfg).train(tmp_path / "all", progress=False)
    assert list(ckpt.checkpoint_steps(tmp_path / "all" / "checkpoints")) == [0, 50, 100, 150, 200]
    with pytest.raises(InputError, match="checkpoint_keep=-1"):
        DQN(apply_overrides(cfg, ["checkpoint_keep=-1"])).train(tmp_path / "bad", progress=False)
    assert not (tmp_path / "bad").exists()


# --- resuming what a crash or a damaged disk left ------------------------------------------------------------


def _resume_in_process(run: Path, monkeypatch, capsys, *overrides: str) -> tuple[int, str]:
    from rlpipe.scripts.cli import main

    monkeypatch.chdir(run.parent)
    capsys.readouterr()
    code = main(["train", "dqn", *overrides, "--resume", str(run), "--no-progress"])
    return code, capsys.readouterr().err


def _flip_a_byte(path: Path) -> None:
    """A byte in the data of the file's largest member (the replay buffer's): torch.load would read it
    without a word; the zip's CRC does not match. (A byte at the file's middle may land in a member's
    alignment padding, which no checksum covers.)"""
    import struct
    import zipfile

    with zipfile.ZipFile(path) as archive:
        largest = max(archive.infolist(), key=lambda info: info.compress_size)
    data = bytearray(path.read_bytes())
    name_len, extra_len = struct.unpack("<HH", data[largest.header_offset + 26:largest.header_offset + 30])
    start = largest.header_offset + 30 + name_len + extra_len
    data[start + largest.compress_size // 2] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", ["flipped-byte", "garbage", "folder-missing"])
def test_resume_falls_back_on_the_newest_whole_checkpoint(saved_run, tmp_path, monkeypatch, capsys, damage):
    run = copy_run(saved_run, tmp_path / "run")
    newest = run / "checkpoints" / f"step_{N:010d}"
    if damage == "flipped-byte":
        _flip_a_byte(newest / "state.pt")
    elif damage == "garbage":
        (newest / "state.pt").write_bytes(b"\0" * 100)
    else:
        shutil.rmtree(newest)
    code, err = _resume_in_process(run, monkeypatch, capsys, f"num_iterations={2 * N}")
    assert code == 0, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and f"step_{N:010d}" in lines[0] and "resuming from step_0000000100" in lines[0], err
    rows = metric_rows(run)
    assert_no_duplicated_steps(rows)
    assert [int(r["step"]) for r in rows if r["average_return"]] == [0, 100, 200, 300, 400]
    assert list(ckpt.checkpoint_steps(run / "checkpoints")) == [300, 400]


def test_resume_without_latest_takes_the_newest_whole_checkpoint(saved_run, tmp_path, monkeypatch, capsys):
    """A kill between a first checkpoint moving in and `latest` being written leaves no `latest`."""
    run = copy_run(saved_run, tmp_path / "run")
    (run / "checkpoints" / "latest").unlink()
    code, err = _resume_in_process(run, monkeypatch, capsys, f"num_iterations={N + 100}")
    assert code == 0, err
    assert json.loads((run / "summary.json").read_text())["updates"] == N + 100


@pytest.mark.parametrize("tail", [b"25", b"\0" * 200], ids=["torn-row", "zeroed-tail"])
def test_a_torn_last_metrics_row_is_dropped_on_resume(saved_run, tmp_path, monkeypatch, capsys, tail):
    """A crash (or a full disk) mid-row leaves the start of a row (here of step 250's: '25'); a power
    cut can leave zeroes. Neither is read as a row, nor stops the resume."""
    run = copy_run(saved_run, tmp_path / "run")
    whole = metric_rows(run)
    with (run / "metrics.csv").open("ab") as fh:
        fh.write(tail)
    code, err = _resume_in_process(run, monkeypatch, capsys, f"num_iterations={2 * N}")
    assert code == 0, err
    rows = metric_rows(run)
    assert rows[: len(whole)] == whole
    assert all(None not in r and None not in r.values() for r in rows), "a junk row was kept"
    assert_no_duplicated_steps(rows)
    assert [int(r["step"]) for r in rows if r["average_return"]] == [0, 100, 200, 300, 400]


def test_summary_json_is_strict_json_when_the_return_is_nan(tmp_path):
    from torchrl.envs import RewardScaling

    from rlpipe.envs import make_env

    cfg = apply_overrides(preset("dqn"), ["initial_collect_steps=20", "num_iterations=10", "eval_interval=0",
                                          "num_eval_episodes=1"])
    # NaN rewards in the evaluation only: training on them would stop the run as diverged
    nan_rewards = lambda: make_env("CartPole-v0").append_transform(RewardScaling(0.0, float("nan")))  # noqa: E731
    result = DQN(cfg, env=lambda: make_env("CartPole-v0"), eval_env=nan_rewards).train(tmp_path / "run", progress=False)
    assert result.summary["final_average_return"] != result.summary["final_average_return"]  # NaN in Python

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    summary = json.loads((tmp_path / "run" / "summary.json").read_text(), parse_constant=refuse)
    assert summary["final_average_return"] is None
