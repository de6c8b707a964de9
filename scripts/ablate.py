"""``rlpipe ablate td3``: the TD3 tutorial's ablation exercise as one command.

    rlpipe ablate td3 --envs Pendulum-v1,HalfCheetah-v5 --seeds 3 --steps 30000 [--workers 2] [--out DIR]

Runs the full agent and the six leave-one-out variants on every env and seed, each as its own run
(`rlpipe train` in a child process, so a crash or Ctrl-C loses at most the runs in flight), up to
``--workers`` at a time. Rerunning the same command skips finished runs and resumes interrupted ones
from their checkpoints. Then it writes ``ablation.csv``, ``ablation.md``, ``curves_<env>.png``,
``ecdf_final_returns.png`` and ``report.html`` (the same tables and figures on one page, each run
linked to its own page) into ``--out``; each run's log (``seedN.log``) holds its live log lines.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path


def add_parser(sub) -> None:
    ablate = sub.add_parser("ablate", help="leave-one-out ablation study over TD3's six ingredients")
    ablate.add_argument("algo", choices=["td3"])
    ablate.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides applied to every run")
    ablate.add_argument("--envs", default="Pendulum-v1", help="comma-separated env ids (default Pendulum-v1)")
    ablate.add_argument("--seeds", type=int, default=3, help="seeds per env and variant (default 3)")
    ablate.add_argument("--steps", type=int, default=30_000, help="env steps per run, start-up included (default 30000)")
    ablate.add_argument("--evals", type=int, default=10, help="evaluations per run, evenly spaced (default 10)")
    ablate.add_argument("--eval-episodes", type=int, default=10, help="episodes per evaluation (default 10)")
    ablate.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="runs in parallel (default: cores)")
    ablate.add_argument("--variants", help="comma-separated subset of variants (default: full and all six no_*)")
    ablate.add_argument("--out", type=Path, default=Path("runs/ablation-td3"), help="study directory")
    ablate.set_defaults(func=run)


@dataclass
class Job:
    env: str
    variant: str
    seed: int
    run_dir: Path
    overrides: list[str]
    preset: str

    def state(self) -> str:
        if (self.run_dir / "summary.json").exists():
            return "done"
        if (self.run_dir / "checkpoints" / "latest").exists():
            return "resume"
        return "new"

    def command(self) -> list[str]:
        base = [sys.executable, "-m", "rlpipe.scripts.cli", "train", self.preset, *self.overrides, "--no-progress"]
        if self.state() == "resume":
            return base + ["--resume", str(self.run_dir)]
        return base + ["--out", str(self.run_dir)]


def _preset_for(env: str) -> str:
    return {"HalfCheetah-v5": "td3-halfcheetah", "Hopper-v5": "td3-hopper"}.get(env, "td3")


def plan(args) -> list[Job]:
    from rlpipe.envs import resolve_env_id
    from rlpipe.pipelines import resolve_preset
    from rlpipe.pipelines.config import WORKERS_PER_CPU, apply_overrides
    from rlpipe.pipelines.errors import InputError
    from rlpipe.pipelines.td3 import INGREDIENTS

    for name in ("seeds", "steps", "evals", "eval_episodes", "workers"):
        if getattr(args, name) <= 0:
            raise InputError(f"--{name.replace('_', '-')}={getattr(args, name)}: expected a positive integer")
    most = WORKERS_PER_CPU * (os.cpu_count() or 1)
    if args.workers > most:
        raise InputError(f"--workers={args.workers}: each run is a process of its own; expected at most {most} on this "
                         f"machine's {os.cpu_count() or 1} CPUs")
    all_variants = ("full", *(f"no_{i}" for i in INGREDIENTS))
    variants = all_variants if not args.variants else tuple(v.strip() for v in args.variants.split(","))
    for v in variants:
        if v not in all_variants:
            raise InputError(f"--variants: unknown variant {v!r}; expected some of {', '.join(all_variants)}")
    envs = [e.strip() for e in args.envs.split(",") if e.strip()]
    if not envs:
        raise InputError("--envs is empty; expected comma-separated env ids such as Pendulum-v1,HalfCheetah-v5")
    jobs = []
    for env in envs:
        resolve_env_id(env)  # an unknown id first, with the closest known ones
        preset = _preset_for(env)
        _, base = resolve_preset(preset)
        # Budgets in whole collector blocks, so evaluations land on the iterations they name.
        block = base.collector.frames_per_batch
        start = min(base.initial_collect_steps, args.steps // 10) // block * block
        iterations = args.steps - start
        if iterations < block * args.evals:
            raise InputError(f"--steps={args.steps}: too few for {args.evals} evaluations; expected at least "
                             f"{start + block * args.evals}")
        eval_interval = iterations // args.evals // block * block
        budget = [
            f"env={env}",
            f"initial_collect_steps={start}",
            f"learning_starts={min(base.first_update_frame, max(start, base.batch_size))}",
            f"num_iterations={iterations}",
            f"eval_interval={eval_interval}",
            f"num_eval_episodes={args.eval_episodes}",
            f"checkpoint_interval={eval_interval}",
            f"policy_save_interval={iterations}",
            f"log_interval={eval_interval}",
            # Each run steps its env in its learner's process: the study already keeps the cores
            # busy with --workers runs side by side (user overrides, after these, still win).
            "collector.sync=true",
        ]
        _check_env(base, [*budget, *args.overrides])
        for variant in variants:
            switch = [] if variant == "full" else [f"{variant.removeprefix('no_')}=false"]
            for seed in range(args.seeds):
                overrides = [*budget, *args.overrides, *switch, f"seed={seed}"]
                apply_overrides(base, overrides)  # bad keys stop here, before anything runs
                run_dir = args.out / env.replace("/", "_") / variant / f"seed{seed}"
                jobs.append(Job(env, variant, seed, run_dir, overrides, preset))
    return jobs


def _check_env(base, overrides: list[str]) -> None:
    """The env as every run of the study will make it (its action space, the extra it needs, the
    memory the run takes): an env that cannot work stops the study before any run starts."""
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.pipelines.td3 import TD3

    pipeline = TD3(apply_overrides(base, overrides))
    pipeline.env.close()
    pipeline.eval_env.close()


# How long a run may take to save its checkpoint and exit once passed a stop signal, before it is killed.
RUN_STOP_TIMEOUT = 120.0


def stop_runs(procs: list[subprocess.Popen], signum: int, timeout: float) -> None:
    """Pass ``signum`` to each of ``procs`` and wait for them to exit, ``timeout`` seconds in all; one
    still running then is killed (its collector processes end when they lose it)."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signum)
    deadline = time.monotonic() + timeout
    for proc in procs:
        try:
            proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            print(f"rlpipe: run {proc.pid} did not stop within {timeout:g} s of {signal.Signals(signum).name}; "
                  "killing it", file=sys.stderr)
            proc.kill()
            proc.wait(timeout=10.0)


def run(args) -> int:
    from tqdm.auto import tqdm

    from rlpipe.pipelines.analysis import collect_runs, write_ablation_report
    from rlpipe.pipelines.artifacts.files import write_json_atomic
    from rlpipe.pipelines.errors import InputError
    from rlpipe.pipelines.system.runtime import DeferredInterrupt
    from rlpipe.scripts.output_paths import check_output_dir

    jobs = plan(args)
    check_output_dir(args.out)
    args.out.mkdir(parents=True, exist_ok=True)
    study_file = args.out / "study.json"
    study = {"algo": args.algo, "envs": args.envs, "seeds": args.seeds, "steps": args.steps, "overrides": args.overrides,
             "variants": sorted({j.variant for j in jobs})}
    if study_file.exists():
        previous = json.loads(study_file.read_text())
        if {k: previous.get(k) for k in ("steps", "overrides")} != {k: study[k] for k in ("steps", "overrides")}:
            raise InputError(f"{args.out}: holds a study with other settings ({previous}); expected the same --steps "
                             "and overrides to resume it, or another --out")
    write_json_atomic(study_file, study)

    todo = [j for j in jobs if j.state() != "done"]
    for j in todo:
        # A run that died before its first checkpoint has nothing to resume: start it again.
        if j.state() == "new" and j.run_dir.exists():
            shutil.rmtree(j.run_dir)
        j.run_dir.parent.mkdir(parents=True, exist_ok=True)
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), unit="run", desc="ablation", dynamic_ncols=True)
    running: list[tuple[Job, subprocess.Popen]] = []
    failed: list[Job] = []
    # Ctrl-C, SIGTERM or SIGHUP (to this process alone, or to its group, which the runs are in): the
    # runs are passed the same signal, each saves a checkpoint, and a rerun resumes them. The first
    # signal only sets a flag, so no run is started without being in `running`.
    stop = DeferredInterrupt()
    try:
        with stop:
            while (todo or running) and not stop.requested:
                while todo and len(running) < args.workers:
                    job = todo.pop(0)
                    log = open(job.run_dir.parent / f"{job.run_dir.name}.log", "a")
                    proc = subprocess.Popen(job.command(), stdout=log, stderr=subprocess.STDOUT,
                                            env={**os.environ, "OMP_NUM_THREADS": "1"})
                    log.close()
                    running.append((job, proc))
                time.sleep(0.5)
                for job, proc in list(running):
                    if proc.poll() is not None:
                        running.remove((job, proc))
                        if proc.returncode != 0:
                            failed.append(job)
                        bar.update(1)
                bar.set_postfix(running=len(running), failed=len(failed), refresh=False)
            if stop.requested:
                stop_runs([proc for _, proc in running], stop.signum, RUN_STOP_TIMEOUT)
                print(f"rlpipe: interrupted; rerun the same command to resume {args.out}", file=sys.stderr)
                return 128 + stop.signum
    except KeyboardInterrupt as exc:  # a second signal: stop now, unsaved
        stop_runs([proc for _, proc in running], signal.SIGKILL, 10.0)
        print(f"rlpipe: interrupted; rerun the same command to resume {args.out}", file=sys.stderr)
        return getattr(exc, "exit_status", 130)
    finally:
        bar.close()
    if failed:
        names = ", ".join(f"{j.env}/{j.variant}/seed{j.seed}" for j in failed)
        raise InputError(f"{len(failed)} runs failed ({names}); see their .log files under {args.out}")

    variant_of = {str(j.run_dir): j.variant for j in jobs}
    records, curves = collect_runs([j.run_dir for j in jobs], variant=variant_of)
    paths = write_ablation_report(records, curves, args.out)
    for p in paths:
        print(p)
    return 0
