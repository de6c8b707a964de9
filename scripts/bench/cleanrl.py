"""``rlpipe bench cleanrl``: SAC, TD3 and DQN against CleanRL's single-file scripts, in one run.

Each case runs CleanRL's script (``scripts/bench/peers/cleanrl.py``: cleanrl 1.2.0 in a venv of its own)
with its defaults, with torch's default threads and with one thread, and rlpipe with the same
hyperparameters (taken from the script's own defaults). Both sides are timed over two lengths,
``learning_starts + n1`` and ``learning_starts + n2`` env steps, so start-up (imports, the random
warm-up, process starts) cancels: updates/s = (U2 - U1) / (t2 - t1), wall clock of each run.

rlpipe runs on its presets' collection (SAC/TD3: the env steps in a collector process beside the
learner; DQN: ``dqn-cleanrl``, 16 env copies stepped as one batch in that process) with its
learner on one thread and on all cores (``num_threads``), the best of the two compared. DQN on an ALE id
(``--algos dqn --envs ALE/Breakout-v5``) is CleanRL's ``dqn_atari.py`` against the ``dqn-atari`` preset
(``ATARI_ARGS``).
"""

from __future__ import annotations

import csv
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

CASES = {"sac": ("Pendulum-v1", "HalfCheetah-v5"), "td3": ("Pendulum-v1", "HalfCheetah-v5"), "dqn": ("CartPole-v1",)}
# env steps after learning_starts of the two timed runs (DQN makes one update per 10 of them, on Atari per 4)
LENGTHS = {"sac": (300, 1800), "td3": (300, 1800), "dqn": (5000, 35000), "dqn_atari": (2000, 10000)}
# DQN on an Atari id (``--algos dqn --envs ALE/Breakout-v5``) runs CleanRL's dqn_atari.py against rlpipe's
# dqn-atari preset (its settings), both with these two changed: SB3's replay buffer, which the script uses,
# allocates every slot at the start (1,000,000 stacks of 4x84x84 uint8 = 28 GB, more than this machine has), and
# the random warm-up is shortened (it cancels between the two lengths). Exploration ends before learning starts
# on both sides (CleanRL's schedule spans 10% of its run; rlpipe's is set to 2,000 steps), so every timed step
# runs the Q-network.
ATARI_ARGS = ("--learning-starts", "20000", "--buffer-size", "100000")


def _is_atari(env_id: str) -> bool:
    return env_id.startswith("ALE/")


def rlpipe_overrides(algo: str, env_id: str, hp: dict, act_dim: int) -> tuple[str, list[str]]:
    """(preset, overrides) giving rlpipe CleanRL's hyperparameters ``hp`` (its script's defaults)."""
    quiet = ["eval_interval=0", "num_eval_episodes=5", "log_interval=500", "checkpoint_interval=1000000",
             "policy_save_interval=1000000"]
    if algo == "dqn_atari":
        return "dqn-atari", [f"env={env_id}", f"initial_collect_steps={hp['learning_starts']}",
                             f"replay_buffer_capacity={int(hp['buffer_size'])}", "epsilon_decay_steps=2000", *quiet]
    if algo == "dqn":
        return "dqn-cleanrl", [f"env={env_id}", *quiet]
    common = [f"env={env_id}", f"initial_collect_steps={hp['learning_starts']}", f"gamma={hp['gamma']}",
              f"target_update_tau={hp['tau']}", f"batch_size={hp['batch_size']}",
              f"replay_buffer_capacity={int(hp['buffer_size'])}", *quiet]
    if algo == "sac":
        return "sac", [*common, f"actor_learning_rate={hp['policy_lr']}", f"critic_learning_rate={hp['q_lr']}",
                       f"alpha_learning_rate={hp['q_lr']}", f"target_entropy={-float(act_dim)}"]
    return "td3", [*common, "actor_fc_layer_params=[256,256]", "critic_fc_layer_params=[256,256]",
                   f"learning_rate={hp['learning_rate']}", f"exploration_noise={hp['exploration_noise']}",
                   f"policy_noise={hp['policy_noise']}", f"noise_clip={hp['noise_clip']}",
                   f"policy_delay={hp['policy_frequency']}", f"learning_starts={hp['learning_starts']}"]


def timed_train(preset: str, overrides: list[str], out: Path) -> dict:
    """``rlpipe train PRESET ...`` in a fresh process, as a user starts it: its wall time and summary.

    A fresh process per run, like the peers' scripts: runs inside one process would leave the
    one-time costs (imports, first env load, lazy initialisations) to the first, and the two
    lengths would no longer cancel start-up.
    """
    cmd = [sys.executable, "-m", "rlpipe.scripts.cli", "train", preset, *overrides, "--out", str(out), "--no-progress"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode:
        last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"rlpipe run failed (exit {proc.returncode}): {last} ({shlex.join(cmd)})")
    return {"wall_s": wall, "summary": json.loads((out / "summary.json").read_text()), "command": shlex.join(cmd)}


def rlpipe_speed(preset: str, overrides: list[str], lengths: tuple[int, int], steps_per_update: int,
                 seed: int, out: Path) -> dict:
    """rlpipe's updates/s from two runs (``lengths`` env steps after the start-up), wall clock of each."""
    runs = [timed_train(preset, [*overrides, f"num_iterations={n // steps_per_update}", f"seed={seed}"], out / f"{preset}-{n}")
            for n in lengths]
    a, b = (r["summary"] for r in runs)
    dt = runs[1]["wall_s"] - runs[0]["wall_s"]
    return {"updates_per_s": (b["updates"] - a["updates"]) / dt, "env_steps_per_s": (b["frames"] - a["frames"]) / dt,
            "updates_per_s_in_run": in_run_updates_per_s(out / f"{preset}-{lengths[1]}" / "metrics.csv"),
            "final_average_return": b["final_average_return"], "runs": runs, "overrides": overrides, "preset": preset}


def in_run_updates_per_s(metrics_csv: Path) -> float | None:
    """Updates/s inside a run, after learning starts: from its log rows past the first one that
    counts updates (that one spans the random start-up). A second figure beside the two-length one,
    which a start-up of varying length (random steps at the env's speed) can blur."""
    with metrics_csv.open(newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get("updates_per_s") and int(r["updates"]) > 0]
    rows = rows[1:]
    if not rows:
        return None
    return sum(float(r["updates_per_s"]) for r in rows) / len(rows)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.0f}"


def bench_cleanrl(args, out: Path) -> dict:
    import gymnasium

    from rlpipe.scripts.bench.peers import cleanrl

    algos = args.algos or list(CASES)
    rows, figures = [], {"cases": []}
    for name in algos:
        for env_id in (args.envs or CASES[name]):
            algo = "dqn_atari" if name == "dqn" and _is_atari(env_id) else name
            extra = ATARI_ARGS if algo == "dqn_atari" else ()
            hp = cleanrl.defaults(algo)
            hp.update({k: type(hp[k])(v) for k, v in zip([f[2:].replace("-", "_") for f in extra[::2]], extra[1::2])})
            lengths = tuple(args.lengths) if args.lengths else LENGTHS[algo]
            act_dim = 0 if name == "dqn" else int(gymnasium.make(env_id).action_space.shape[-1])
            preset, overrides = rlpipe_overrides(algo, env_id, hp, act_dim)
            every = int(hp.get("train_frequency", 1))
            mine = {}
            for threads in sorted({1, os.cpu_count() or 1}):
                mine[threads] = rlpipe_speed(preset, [*overrides, f"num_threads={threads}", *args.overrides], lengths,
                                             every, args.seed, out / f"{algo}-{env_id.replace('/', '_')}-threads{threads}")
                print(f"  rlpipe {algo} {env_id} learner threads={threads}: {mine[threads]['updates_per_s']:.1f} updates/s",
                      file=sys.stderr)
            ours = max(mine.values(), key=lambda r: r["updates_per_s"])
            peers = {}
            for threads in (None, 1):
                peers[threads or "default"] = peer = cleanrl.cleanrl_speed(algo, env_id, lengths, seed=args.seed,
                                                                           threads=threads, extra_args=extra)
                print(f"  CleanRL {algo} {env_id} threads={threads or 'default'}: {peer['updates_per_s']:.1f} updates/s",
                      file=sys.stderr)
            best = max(p["updates_per_s"] for p in peers.values())
            peer_returns = peers["default"]["episodic_returns"]
            figures["cases"].append({"algo": name, "script": cleanrl.ALGOS[algo], "env": env_id, "lengths": lengths,
                                     "rlpipe": {str(k): v for k, v in mine.items()},
                                     "cleanrl": {str(k): v for k, v in peers.items()}})
            rows.append(
                f"| {name.upper()} | {env_id} | "
                f"{' / '.join(format(r['updates_per_s'], '.0f') for r in mine.values())} "
                f"({ours['env_steps_per_s']:.0f}) | "
                f"{peers['default']['updates_per_s']:.0f} ({peers['default']['env_steps_per_s']:.0f}) | "
                f"{peers[1]['updates_per_s']:.0f} | **{ours['updates_per_s'] / best:.2f}** | "
                f"{_fmt(ours['updates_per_s_in_run'])} / {_fmt(peers['default'].get('updates_per_s_in_run'))} / "
                f"{_fmt(peers[1].get('updates_per_s_in_run'))} | "
                f"{ours['final_average_return']:.1f} | "
                f"{statistics.mean(peer_returns) if peer_returns else float('nan'):.1f} |"
            )
    table = "\n".join([
        f"rlpipe against CleanRL 1.2.0 (its scripts, its defaults), seed {args.seed}; each side timed over two lengths "
        "after learning_starts (start-up cancels), each on each thread setting; the ratio takes each side's best.",
        "",
        f"| algorithm | env | rlpipe updates/s, learner on {' / '.join(str(k) for k in sorted({1, os.cpu_count() or 1}))} "
        "thread(s) (env steps/s of the best) | CleanRL, torch's default threads | CleanRL, 1 thread | "
        "rlpipe / CleanRL's best | in-run updates/s: rlpipe (best) / CleanRL default / CleanRL 1 thread | "
        "rlpipe final AverageReturn (greedy, 5 episodes) | CleanRL last 10 training episodes |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
    ])
    return {**figures, "table": table}
