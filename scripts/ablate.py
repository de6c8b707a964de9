"""``rlpipe ablate td3``: the TD3 tutorial's ablation exercise as one command.

    rlpipe ablate td3                      # the default study: STUDY_ENVS x 7 variants x 5 seeds, ~73-90 min on 2 cores
    rlpipe ablate td3 --envs Pendulum-v1,HalfCheetah-v5 --seeds 3 --steps 30000 [--workers 2] [--out DIR]

Runs the full agent and the six leave-one-out variants on every env and seed, each as its own run
(`rlpipe train` in a child process, one torch thread, the env stepped in that process), up to
``--workers`` at a time (default: one per core). Rerunning the same command skips finished runs and
starts the unfinished ones again (``--continue restart``: a stopped and continued study ends with the
same results as an uninterrupted one), or resumes them from their checkpoints (``--continue
checkpoint``: less work lost; a run resumed from its checkpoint is exact too, as its envs' state is
checkpointed, except on an env rlpipe cannot capture, such as Box2D's). Then it writes ``ablation.csv``, ``ablation.md``,
``curves_<env>.png``, ``ecdf_final_returns.png``, the across-env statistics (``aggregate.csv``,
``aggregate_iqm.png``, ``performance_profile.png``, ``probability_of_improvement.png``) and
``report.html`` into ``--out``; each run's log (``seedN.log``) holds its live log lines.

The default study's budget, from the CPU seconds of single full-agent runs of it, measured on this
2-core machine while other jobs loaded it to 5-12 (so wall times were 5-10x these; CPU seconds, from
`time rlpipe ablate td3 --envs ENV --seeds 1 --variants full --workers 1`, are what two runs side by
side on two free cores each take; noisy, so rounded up; each includes ~10 s of start, plan and report):

    env                  nets, lr, batch           steps    CPU s per run   full agent (seed 0)
    Pendulum-v1          [64,64], 1e-3, 256        20,000   ~65 (134.5 s for 2)   -156 (seed 1: -136)
    InvertedPendulum-v5  [64,64], 1e-3, 256        30,000   ~100 (99.2)            1000 from 17,400 on
    Hopper-v5            [128,128], 1e-3, 100      50,000   ~145 (144.4)           1043 (random: 28)

    7 variants x 5 seeds x (65 + 100 + 145) s = 10,850 run-seconds; two at a time: ~90 minutes,
    less the start/report share counted in every run (~35 x 3 x 10 s / 2 = ~17 min): ~73-90 minutes.
    no_delayed_policy_updates updates its actor twice as often (+~3% in all); no_experience_replay
    learns from batches of 1 (cheaper).
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
    ablate.add_argument("--envs", default=",".join(STUDY_ENVS),
                        help=f"comma-separated env ids (default: the default study's, {','.join(STUDY_ENVS)})")
    ablate.add_argument("--seeds", type=int, default=5, help="seeds per env and variant (default 5)")
    ablate.add_argument("--steps", type=int, default=None,
                        help="env steps per run, random start-up steps included (default: each study env's own "
                             f"budget, {', '.join(f'{e} {s.steps:,}' for e, s in STUDY_ENVS.items())}; "
                             f"{DEFAULT_STEPS:,} for other envs)")
    ablate.add_argument("--evals", type=int, default=10, help="evaluations per run, evenly spaced (default 10)")
    ablate.add_argument("--eval-episodes", type=int, default=None,
                        help="episodes per evaluation (default: 10 on Pendulum-v1 and other envs, 5 on the "
                             "default study's MuJoCo envs, whose episodes are up to 1,000 steps)")
    ablate.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="runs in parallel (default: cores)")
    ablate.add_argument("--variants", help="comma-separated subset of variants: full, and no_INGREDIENT or "
                        "INGREDIENT for each ingredient left out (default: full and all six)")
    ablate.add_argument("--continue", dest="continue_mode", choices=["restart", "checkpoint"], default="restart",
                        help="what a rerun does with a run that did not finish: start it again (default) or resume "
                             "it from its checkpoint (less work lost); either way the results equal an "
                             "uninterrupted study's, except on an env whose state rlpipe cannot capture (Box2D)")
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
    steps: int = 0
    resume: bool = False

    def state(self) -> str:
        if (self.run_dir / "summary.json").exists():
            return "done"
        if self.resume and (self.run_dir / "checkpoints" / "latest").exists():
            return "resume"
        return "new"

    def progress(self) -> int:
        """Env steps this run has logged so far (its last metrics row's ``frames``)."""
        try:
            with (self.run_dir / "metrics.csv").open() as fh:
                header = fh.readline().rstrip("\n").split(",")
                last = None
                for last in fh:  # noqa: B007 - the last line is wanted
                    pass
            return int(float(last.split(",")[header.index("frames")])) if last else 0
        except (OSError, ValueError, IndexError):
            return 0

    def command(self) -> list[str]:
        base = [sys.executable, "-m", "rlpipe.scripts.cli", "train", self.preset, *self.overrides, "--no-progress"]
        if self.state() == "resume":
            return base + ["--resume", str(self.run_dir)]
        return base + ["--out", str(self.run_dir)]


def _preset_for(env: str) -> str:
    return {"HalfCheetah-v5": "td3-halfcheetah", "Hopper-v5": "td3-hopper"}.get(env, "td3")


@dataclass(frozen=True)
class StudyEnv:
    """One env of the default study: its budget and the settings that make the full agent learn in it."""

    steps: int
    random_steps: int
    eval_episodes: int
    overrides: tuple[str, ...]


# The default study: networks, learning rate and batch per env that learn it within its steps on 2 cores
# (Pendulum and InvertedPendulum: 2x64, lr 1e-3, batch 256; Hopper, where the TD3 paper's ingredients matter: its
# lr 1e-3 and batch 100 on 128-unit layers, ~2.3x the steps per second of (400, 300), and 10,000 random steps).
# The one-seed tries that chose them: BENCHMARKS.md, "The TD3 ablation study".
STUDY_ENVS = {
    "Pendulum-v1": StudyEnv(20_000, 1000, 10, ("actor_fc_layer_params=[64,64]", "critic_fc_layer_params=[64,64]",
                                                "batch_size=256", "learning_rate=1e-3")),
    "InvertedPendulum-v5": StudyEnv(30_000, 1000, 5, ("actor_fc_layer_params=[64,64]", "critic_fc_layer_params=[64,64]",
                                                      "batch_size=256", "learning_rate=1e-3")),
    "Hopper-v5": StudyEnv(50_000, 10_000, 5, ("actor_fc_layer_params=[128,128]", "critic_fc_layer_params=[128,128]",
                                            "batch_size=100", "learning_rate=1e-3")),
}
DEFAULT_STEPS = 30_000  # envs outside the default study


def _variant_names(spec: str | None, ingredients: tuple[str, ...]) -> tuple[str, ...]:
    from rlpipe.pipelines.errors import InputError

    all_variants = ("full", *(f"no_{i}" for i in ingredients))
    if not spec:
        return all_variants
    names = []
    for v in (v.strip() for v in spec.split(",")):
        name = v if v in all_variants else f"no_{v}"
        if name not in all_variants:
            raise InputError(f"--variants: unknown variant or ingredient {v!r}; expected full, or an ingredient "
                             f"(or no_ it): {', '.join(ingredients)}")
        if name not in names:
            names.append(name)
    return tuple(names)


def plan(args) -> list[Job]:
    from rlpipe.envs import resolve_env_id
    from rlpipe.pipelines import resolve_preset
    from rlpipe.pipelines.config import WORKERS_PER_CPU, apply_overrides
    from rlpipe.pipelines.errors import InputError
    from rlpipe.pipelines.td3 import INGREDIENTS

    for name in ("seeds", "steps", "evals", "eval_episodes", "workers"):
        if getattr(args, name) is not None and getattr(args, name) <= 0:
            raise InputError(f"--{name.replace('_', '-')}={getattr(args, name)}: expected a positive integer")
    most = WORKERS_PER_CPU * (os.cpu_count() or 1)
    if args.workers > most:
        raise InputError(f"--workers={args.workers}: each run is a process of its own; expected at most {most} on this "
                         f"machine's {os.cpu_count() or 1} CPUs")
    variants = _variant_names(args.variants, INGREDIENTS)
    envs = [e.strip() for e in args.envs.split(",") if e.strip()]
    if not envs:
        raise InputError("--envs is empty; expected comma-separated env ids such as Pendulum-v1,HalfCheetah-v5")
    for item in args.overrides:
        if item.partition("=")[0].strip() in ("num_iterations", "env", "seed"):
            raise InputError(f"override {item!r}: the study sets it (num_iterations from --steps, env from --envs, "
                             "seed from --seeds); expected --steps, --envs or --seeds instead")
    per_env = []
    for env in envs:
        resolve_env_id(env)  # an unknown id first, with the closest known ones
        preset = _preset_for(env)
        _, base = resolve_preset(preset)
        study = STUDY_ENVS.get(env)
        steps = args.steps or (study.steps if study else DEFAULT_STEPS)
        settings = list(study.overrides) if study else []
        # The random start-up steps: a user's initial_collect_steps=, the study env's own at its own
        # budget, else at most a tenth of the budget (the study env's or preset's, if fewer); in whole collector blocks, so evaluations land on the
        # iterations they name.
        user = apply_overrides(apply_overrides(base, settings), args.overrides)
        block = user.collector.frames_per_batch
        if any(o.partition("=")[0].strip() == "initial_collect_steps" for o in args.overrides):
            start = user.initial_collect_steps
        elif study and args.steps is None:
            start = study.random_steps
        else:  # another --steps keeps at most a tenth of it random
            start = min(study.random_steps if study else base.initial_collect_steps, steps // 10) // block * block
        if steps <= start:
            raise InputError(f"--steps={steps} for {env}: not more than its {start} random start-up steps "
                             "(initial_collect_steps), so the agent would never learn; expected more steps than that")
        iterations = steps - start
        if iterations < block * args.evals:
            raise InputError(f"--steps={steps}: too few for {args.evals} evaluations on {env}; expected at least "
                             f"{start + block * args.evals}")
        eval_interval = iterations // args.evals // block * block
        episodes = args.eval_episodes or (study.eval_episodes if study else 10)
        budget = [
            f"env={env}",
            *settings,
            f"initial_collect_steps={start}",
            f"learning_starts={min(user.first_update_frame, max(start, user.batch_size))}",
            f"num_iterations={iterations}",
            f"eval_interval={eval_interval}",
            f"num_eval_episodes={episodes}",
            # Restarted runs need no checkpoint but the one a stop signal makes.
            f"checkpoint_interval={eval_interval if args.continue_mode == 'checkpoint' else iterations}",
            f"policy_save_interval={iterations}",
            f"log_interval={max(block, eval_interval // 2)}",
            # Each run steps its env in its learner's process with one torch thread: the study keeps the
            # cores busy with --workers runs side by side (user overrides, after these, still win).
            "collector.sync=true",
            "collector.workers=1",
            "num_threads=1",
        ]
        _check_env(base, [*budget, *args.overrides])
        per_env.append((env, preset, base, budget, steps))
    jobs = []
    # Seed-major order: each round of seeds covers every env and variant, so a study stopped early
    # already holds comparable runs, and the progress bar's rate (env steps/s) is a fair mix early on.
    for seed in range(args.seeds):
        for env, preset, base, budget, steps in per_env:
            for variant in variants:
                switch = [] if variant == "full" else [f"{variant.removeprefix('no_')}=false"]
                overrides = [*budget, *args.overrides, *switch, f"seed={seed}"]
                apply_overrides(base, overrides)  # bad keys stop here, before anything runs
                run_dir = args.out / env.replace("/", "_") / variant / f"seed{seed}"
                jobs.append(Job(env, variant, seed, run_dir, overrides, preset, steps,
                                resume=args.continue_mode == "checkpoint"))
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
    steps = {j.env: j.steps for j in jobs}
    study = {"algo": args.algo, "envs": args.envs, "seeds": args.seeds, "steps": steps, "overrides": args.overrides,
             "variants": sorted({j.variant for j in jobs}),
             "runs": {str(j.run_dir.relative_to(args.out)): j.overrides for j in jobs}}
    if study_file.exists():
        previous = json.loads(study_file.read_text())
        # A run of the same name must have been started with the same settings to be kept or resumed.
        before = previous.get("runs", {})
        changed = sorted(name for name, overrides in study["runs"].items()
                         if name in before and before[name] != overrides)
        if changed or (not before and previous.get("overrides") != args.overrides):
            raise InputError(f"{args.out}: holds a study with other settings (e.g. {(changed or ['overrides'])[0]}); "
                             "expected the same --steps, --eval-episodes, --evals and overrides to continue it, "
                             "or another --out")
        study["runs"] = {**before, **study["runs"]}
    write_json_atomic(study_file, study)

    todo = [j for j in jobs if j.state() != "done"]
    for j in todo:
        # A run that died before its first checkpoint has nothing to resume: start it again.
        if j.state() == "new" and j.run_dir.exists():
            shutil.rmtree(j.run_dir)
        j.run_dir.parent.mkdir(parents=True, exist_ok=True)
    # The bar counts env steps of the whole study (finished runs' and the running ones' logged steps),
    # so its rate and ETA hold for runs of different lengths; smoothing=0: the rate since the start.
    done_steps = sum(j.steps for j in jobs if j.state() == "done")
    bar = tqdm(total=sum(j.steps for j in jobs), initial=done_steps, unit="step", unit_scale=True, smoothing=0,
               desc=f"ablation ({len(jobs) - len(todo)}/{len(jobs)} runs)", dynamic_ncols=True)
    shown = done_steps
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
                        else:
                            done_steps += job.steps
                            bar.set_description(f"ablation ({len(jobs) - len(todo) - len(running)}/{len(jobs)} runs)",
                                                refresh=False)
                now = done_steps + sum(min(job.progress(), job.steps) for job, _ in running)
                if now > shown:
                    bar.update(now - shown)
                    shown = now
                bar.set_postfix(running=len(running), failed=len(failed), refresh=False)
            if stop.requested:
                stop_runs([proc for _, proc in running], stop.signum, RUN_STOP_TIMEOUT)
                print(f"rlpipe: interrupted; rerun the same command to continue {args.out}", file=sys.stderr)
                return 128 + stop.signum
    except KeyboardInterrupt as exc:  # a second signal: stop now, unsaved
        stop_runs([proc for _, proc in running], signal.SIGKILL, 10.0)
        print(f"rlpipe: interrupted; rerun the same command to continue {args.out}", file=sys.stderr)
        return getattr(exc, "exit_status", 130)
    finally:
        bar.close()
    if failed:
        # Not bad input (exit 2): a run crashed or was killed; the rerun starts it again.
        names = ", ".join(f"{j.env}/{j.variant}/seed{j.seed}" for j in failed)
        print(f"rlpipe: {len(failed)} runs failed ({names}); see their .log files under {args.out}, and rerun the "
              "same command to run them again", file=sys.stderr)
        return 1

    variant_of = {str(j.run_dir): j.variant for j in jobs}
    records, curves = collect_runs([j.run_dir for j in jobs], variant=variant_of)
    paths = write_ablation_report(records, curves, args.out)
    for p in paths:
        print(p)
    return 0
