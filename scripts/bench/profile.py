"""``rlpipe bench profile``: where a training run's time goes in its steady state, per part.

    rlpipe bench profile PRESET [key=value ...] [--steps N] [--duration S] [--rate HZ]

Runs a real ``rlpipe train PRESET`` (the overrides, evaluations off, ``--steps`` iterations) in a
child process, polls its metrics.csv until the first row with updates (learning has started), then
samples it and its children (collector processes) with py-spy for ``--duration`` seconds, idle
samples included so that a learner blocked on a collector's pipe counts as waiting. Each process's
main-thread samples are classified into parts by the frames on their stacks (``classify_learner``,
``classify_worker``: rules written against real stacks of the ``sac``, ``td3`` and ``dqn`` presets'
runs), and the shares print as one Markdown table per process. The run is stopped (SIGTERM, which it
answers with a checkpoint) once sampled.

py-spy is not a dependency of rlpipe: the ``bench`` extra (``pip install -e ".[bench]"``) installs it
(it is looked for next to this Python, then on PATH). It needs to attach to the child (ptrace: root, or ``kernel.yama.ptrace_scope=0``).
"""

from __future__ import annotations

import csv
import functools
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Iterable
from pathlib import Path

Frame = tuple[str, str]
"""(qualified function name, file path) of one frame, as py-spy's raw format writes them."""

LEARNER_PARTS = (
    "replay sample",
    "update: forward (losses)",
    "update: backward (autograd engine)",
    "update: optimiser step",
    "update: target update",
    "weight push to collectors",
    "waiting for a collected block",
    "env step (in-process collector)",
    "collection policy (in-process collector)",
    "collector bookkeeping (in-process: trajectory ids, stacking, copies)",
    "insert a block into the replay buffer",
    "triggers (log rows, checkpoints), loop bookkeeping, other",
)
WORKER_PARTS = (
    "env step",
    "collection policy",
    "collector bookkeeping (trajectory ids, stacking, copies)",
    "waiting for the learner to take the block / weights",
    "other",
)

_HEADER = re.compile(r'process (\d+):"((?:[^"\\]|\\.)*)";')
_THREAD = re.compile(r"thread \((\w+)\)(?::\s*(.*))?$")
_FRAME = re.compile(r"^(.*) \(([^()]*)\)$")


def parse_raw(lines: Iterable[str]) -> dict[int, dict]:
    """py-spy's ``--format raw --threads --subprocesses`` output -> {pid: {"cmd", "parent", "threads":
    {thread name: Counter(stack -> samples)}}}, a stack being a tuple of ``Frame`` from root to leaf.

    A child process's lines start with its ancestors' headers (``process PID:"cmdline";``) and then
    its own; command lines may hold ``;`` (multiprocessing's ``-c`` string), hence the regex."""
    processes: dict[int, dict] = {}
    for line in lines:
        line = line.rstrip("\n")
        if not line.strip():
            continue
        stack_text, _, count = line.rpartition(" ")
        chain, pos = [], 0
        while (m := _HEADER.match(stack_text, pos)) is not None:
            chain.append((int(m.group(1)), m.group(2)))
            pos = m.end()
        if not chain:
            continue
        pid, cmd = chain[-1]
        parts = stack_text[pos:].split(";")
        thread = _THREAD.match(parts[0])
        name = (thread.group(2) or thread.group(1)) if thread else "?"
        frames = tuple(_frame(p) for p in (parts[1:] if thread else parts))
        proc = processes.setdefault(pid, {"cmd": cmd, "parent": chain[-2][0] if len(chain) > 1 else None,
                                          "threads": {}})
        proc["threads"].setdefault(name, Counter())[frames] += int(count)
    return processes


def _frame(text: str) -> Frame:
    m = _FRAME.match(text)
    return (m.group(1), m.group(2)) if m else (text, "")


def _has(stack: tuple[Frame, ...], name: str | None = None, path: str | None = None) -> bool:
    """Whether a frame's function ends with ``name`` (``Loop.run`` or ``.step``) and/or its file contains ``path``."""
    return any((name is None or fn == name or fn.endswith(name)) and (path is None or path in file)
               for fn, file in stack)


def _after(stack: tuple[Frame, ...], name: str) -> tuple[Frame, ...] | None:
    """The frames below the first frame named ``name`` (None if there is none)."""
    for i, (fn, _) in enumerate(stack):
        if fn == name:
            return stack[i + 1:]
    return None


def _rollout(stack: tuple[Frame, ...]) -> tuple[Frame, ...] | None:
    """The frames below a collector's per-step loop: TorchRL's ``Collector.rollout``, or ``GymCollector``'s
    own (``GymCollector._rollout``, which steps the gymnasium env directly); None outside one."""
    frames = _after(stack, "GymCollector._rollout")
    if frames is not None:  # its per-step loop is ``_steps``: what that calls is the step's work
        steps = _after(frames, "GymCollector._steps")
        return steps if steps is not None else frames
    return _after(stack, "Collector.rollout")


def _is_env(stack: tuple[Frame, ...]) -> bool:
    return any("/torchrl/envs/" in file or "/gymnasium/" in file or "/pybullet" in file or "/mujoco/" in file
               or "/envs/" in file and "/site-packages/" not in file for _, file in stack)


def _collector_part(rollout: tuple[Frame, ...]) -> str:
    """What a collector's ``rollout`` is doing: the policy (a module called from the rollout itself),
    the env (its step, reset, transforms, ``step_mdp``), or the collector's own work."""
    if rollout and (rollout[0][0] in ("Module._wrapped_call_impl", "Module._call_impl", "GymCollector._random_step")
                    or rollout[0][1].endswith("/tensor_policy.py")):  # GymCollector's policy on tensors
        return "policy"
    return "env" if _is_env(rollout) else "bookkeeping"


def classify_learner(stack: tuple[Frame, ...], in_process: bool = False) -> str:
    """The part of the learner's work a main-thread sample belongs to (one of ``LEARNER_PARTS``);
    ``in_process``: the learner steps the env itself (TorchRL's ``Collector``; see ``shares``)."""
    loop = _after(stack, "Loop.run")
    if not loop:
        return LEARNER_PARTS[-1]
    top = loop[0][0]
    if top == "Loop.pay_updates":
        if _has(loop, "push_weights"):
            return "weight push to collectors"
        if _has(loop, "ReplayBuffer.sample") or _has(loop, path="/sampling.py"):  # rlpipe's own gather
            return "replay sample"
        if _has(loop, path="target_updates.py") or _has(loop, "Update.step"):
            return "update: target update"
        if _has(loop, path="/optim.py") or _has(loop, path="/torch/optim/") or _has(loop, "zero_grad"):
            return "update: optimiser step"
        if _has(loop, "Tensor.backward") or _has(loop, path="/torch/autograd/"):
            return "update: backward (autograd engine)"
        if len(loop) > 1:  # pipeline.update (or update_step's compiled/graphed wrapper): the losses
            if _has(loop[1:], ".update") or _has(loop[1:], "update_step"):
                return "update: forward (losses)"
        return LEARNER_PARTS[-1]  # check_finite, the loss meters, pay_updates' own lines
    if top == "Loop.collect":
        rollout = _rollout(loop)
        if rollout is not None:  # an in-process Collector, stepping the env here
            return {"policy": "collection policy (in-process collector)", "env": "env step (in-process collector)",
                    "bookkeeping": "collector bookkeeping (in-process: trajectory ids, stacking, copies)"}[
                _collector_part(rollout)]
        if _has(loop, path="/multiprocessing/") or _has(loop, path="/collectors/_multi") or _has(loop, path="/ray/"):
            return "waiting for a collected block"  # collector processes: the learner reads their pipes
        if _has(loop, path="/collectors/_single") or (in_process and _has(loop, path="/torchrl/collectors/")):
            return "collector bookkeeping (in-process: trajectory ids, stacking, copies)"  # around its rollout
        if _has(loop, path="/torchrl/collectors/"):  # a collector's iterator between blocks of its processes
            return "waiting for a collected block"
        return LEARNER_PARTS[-1]
    if top == "Loop.insert":
        return "insert a block into the replay buffer"
    return LEARNER_PARTS[-1]


def classify_worker(stack: tuple[Frame, ...]) -> str:
    """The part of a collector process's work a main-thread sample belongs to (one of ``WORKER_PARTS``)."""
    rollout = _rollout(stack)
    if rollout is not None:
        return {"policy": "collection policy", "env": "env step",
                "bookkeeping": "collector bookkeeping (trajectory ids, stacking, copies)"}[_collector_part(rollout)]
    if _has(stack, path="/multiprocessing/") or _has(stack, path="/torchrl/weight_update/"):
        return "waiting for the learner to take the block / weights"
    return "other" if not _has(stack, path="/torchrl/collectors/") else \
        "collector bookkeeping (trajectory ids, stacking, copies)"


def role(proc: dict) -> str:
    """``learner``, ``collector``, ``evaluator`` or ``other`` (multiprocessing's resource tracker), from the stacks."""
    stacks = [s for c in proc["threads"].values() for s in c]
    if any(_has(s, "Loop.run") for s in stacks):
        return "learner"
    if any(_has(s, path="/torchrl/collectors/") for s in stacks):
        return "collector"
    if any(_has(s, path="/pipelines/evaluation.py") for s in stacks):
        return "evaluator"
    return "other"


def main_thread(proc: dict) -> Counter:
    threads = proc["threads"]
    if "MainThread" in threads:
        return threads["MainThread"]
    # not named: the thread whose stacks do not start in threading's bootstrap
    mains = [c for c in threads.values() if not any(s and s[0][0] == "Thread._bootstrap" for s in c)]
    return max(mains or threads.values(), key=lambda c: sum(c.values()))


def shares(processes: dict[int, dict]) -> list[dict]:
    """Per learner/collector process: its role, main-thread samples and {part: share}, parts in table order."""
    out = []
    for pid, proc in sorted(processes.items()):
        kind = role(proc)
        if kind not in ("learner", "collector"):
            continue
        parts, classify = (LEARNER_PARTS, classify_learner) if kind == "learner" else (WORKER_PARTS, classify_worker)
        counts, main = Counter(), main_thread(proc)
        if kind == "learner":  # TorchRL's in-process Collector: its rollout shows on the learner's stacks
            in_process = any(_rollout(stack) is not None for stack in main)
            classify = functools.partial(classify_learner, in_process=in_process)
        for stack, n in main.items():
            counts[classify(stack)] += n
        total = sum(counts.values())
        out.append({"pid": pid, "role": kind, "samples": total,
                    "shares": {p: counts[p] / total for p in parts if total and counts[p]}})
    return out


def table(figures: list[dict]) -> str:
    lines = []
    for f in figures:
        lines += [f"{f['role']} process (pid {f['pid']}, {f['samples']} samples of its main thread, idle included)", "",
                  f"| part | share of the {f['role']}'s time |", "|---|---|"]
        lines += [f"| {part} | {share * 100:.1f}% |" for part, share in f["shares"].items()]
        lines.append("")
    return "\n".join(lines).rstrip()


# --- running it ---------------------------------------------------------------------------------


def find_py_spy() -> str | None:
    here = Path(sys.executable).parent / "py-spy"
    return str(here) if here.exists() else shutil.which("py-spy")


def _learning_started(metrics_csv: Path) -> dict | None:
    """The first metrics row with updates, if the run has written one."""
    try:
        with metrics_csv.open(newline="") as f:
            for row in csv.DictReader(f):
                if (row.get("updates") or "0").isdigit() and int(row["updates"]) > 0:
                    return row
    except OSError:
        return None
    return None


def _last_row(metrics_csv: Path) -> dict | None:
    """The run's last log row with updates and a wall time, if any."""
    try:
        with metrics_csv.open(newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get("updates_per_s") and r.get("wall_time")]
    except OSError:
        return None
    return rows[-1] if rows else None


def _rate(first: dict | None, last: dict | None) -> float | None:
    """Updates per second of wall time between two log rows (the sampled window, py-spy's pauses included)."""
    if not first or not last or float(last["wall_time"]) <= float(first["wall_time"]):
        return None
    return (int(last["updates"]) - int(first["updates"])) / (float(last["wall_time"]) - float(first["wall_time"]))


def profile_run(preset: str, overrides: list[str], out: Path, *, steps: int, duration: int, rate: int,
                start_timeout: float = 900.0) -> dict:
    py_spy = find_py_spy()
    if py_spy is None:
        raise RuntimeError("py-spy not found next to this Python or on PATH: pip install py-spy")
    out.mkdir(parents=True, exist_ok=True)
    run_dir, raw = out / "run", out / "profile.txt"
    # evaluations off (one episode for the random baseline and the evaluation at step 0, which
    # come before learning), a log row every 100 iterations (when learning starts is read from
    # them); the user's overrides come last and win
    cmd = [sys.executable, "-m", "rlpipe.scripts.cli", "train", preset, "eval_interval=0", "eval_in_background=false",
           "num_eval_episodes=1", "log_interval=100", "checkpoint_interval=100000000",
           "policy_save_interval=100000000", *overrides, f"num_iterations={steps}", "--out", str(run_dir),
           "--no-progress"]
    print("  " + " ".join(cmd[2:]), file=sys.stderr)
    with (out / "train.log").open("w") as log:
        child = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + start_timeout
        while (started := _learning_started(run_dir / "metrics.csv")) is None:
            if child.poll() is not None:
                raise RuntimeError(f"the run ended (exit {child.returncode}) before learning started: see {out / 'train.log'}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"no metrics row with updates after {start_timeout:.0f} s: see {out / 'train.log'}")
            time.sleep(0.5)
        first = _last_row(run_dir / "metrics.csv")
        print(f"  learning started (iteration {started['step']}); sampling {duration:g} s at {rate}/s", file=sys.stderr)
        spy = subprocess.run([py_spy, "record", "--pid", str(child.pid), "--duration", str(duration), "--rate", str(rate),
                              "--format", "raw", "--idle", "--threads", "--subprocesses", "--full-filenames",
                              "--nolineno", "--output", str(raw)], capture_output=True, text=True, check=False)
        if spy.returncode != 0 or not raw.exists():
            raise RuntimeError(f"py-spy failed (exit {spy.returncode}): {spy.stderr.strip()[-500:]}")
        finished_early = child.poll() is not None
        speed = _rate(first, _last_row(run_dir / "metrics.csv"))
    finally:
        _stop(child)
    if finished_early:
        print("  warning: the run ended while being sampled; its end is in the profile (use more --steps)",
              file=sys.stderr)
    figures = shares(parse_raw(raw.read_text().splitlines()))
    return {"command": " ".join(["rlpipe", *cmd[3:]]), "raw": str(raw), "updates_per_s_sampled": speed,
            "processes": figures}


def _stop(child: subprocess.Popen) -> None:
    """SIGTERM (the run saves and stops its workers), then the whole group if it is still there after 60 s."""
    if child.poll() is None:
        child.send_signal(signal.SIGTERM)
        try:
            child.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()


def check_args(args) -> tuple[str, list[str]]:
    """(preset, overrides) of ``rlpipe bench profile``'s arguments; an InputError (before anything is written) if bad."""
    from rlpipe.pipelines import resolve_preset
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.pipelines.errors import InputError

    if not args.overrides or "=" in args.overrides[0]:
        raise InputError("bench profile: expected a preset first: rlpipe bench profile PRESET [key=value ...]")
    preset, overrides = args.overrides[0], args.overrides[1:]
    apply_overrides(resolve_preset(preset)[1], overrides)  # an unknown preset or key is refused here
    if args.duration <= 0 or args.rate <= 0 or (args.steps is not None and args.steps <= 0):
        raise InputError(f"--duration={args.duration} --rate={args.rate} --steps={args.steps}: expected positive integers")
    if find_py_spy() is None:
        raise InputError("bench profile: py-spy not found next to this Python or on PATH; expected it installed "
                         "(pip install -e \".[bench]\" or pip install py-spy)")
    return preset, overrides


def bench_profile(args, out: Path) -> dict:
    preset, overrides = check_args(args)
    steps = args.steps or 100_000
    figures = profile_run(preset, overrides, out, steps=steps, duration=args.duration, rate=args.rate)
    speed = figures["updates_per_s_sampled"]
    figures["table"] = "\n".join([
        f"Steady-state profile: `{figures['command']}`, py-spy {args.rate}/s for {args.duration:g} s after learning "
        f"started" + (f" (the run's updates/s over the sampled window, from its log rows: {speed:.0f})" if speed else ""),
        "",
        table(figures["processes"]),
        "",
        f"Raw samples: {figures['raw']}",
    ])
    return figures
