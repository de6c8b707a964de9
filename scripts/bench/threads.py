"""``rlpipe bench threads``: a run's speed on each learner thread count, alone and beside a busy process.

    rlpipe bench threads --preset td3 [--steps 3000] [--seeds 3] [key=value ...]

Each round runs ``rlpipe train PRESET num_iterations=STEPS num_threads=T`` for every count T from 1 to the
cores there are, first alone, then beside a CPU hog of this command's own (one process spinning for as long
as the run lasts), alternating the counts within the round so that whatever else the machine does falls on
every side alike. The table gives each side's median env steps and updates per second while training (from
``summary.json``) and marks the count ``num_threads=-1`` chooses here (``training.threads.threads_rule``).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HOG = "import time\nend = time.time() + 3600\nwhile time.time() < end: pass"


def _run(preset: str, overrides: list[str], threads: int, out: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    command = [sys.executable, "-m", "rlpipe.scripts.cli", "train", preset, *overrides, f"num_threads={threads}",
               "--out", str(out), "--no-progress"]
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} exited {done.returncode}: {done.stderr.strip()[-500:]}")
    return json.loads((out / "summary.json").read_text())


def bench_threads(args, out: Path) -> dict:
    from rlpipe.pipelines import resolve_preset
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.pipelines.training.threads import cores, threads_rule

    preset = args.preset or "td3"
    overrides = [*args.overrides, *([f"num_iterations={args.steps}"] if args.steps else [])]
    _, cfg = resolve_preset(preset)
    cfg = apply_overrides(cfg, [*overrides, "num_threads=-1"])
    rule, why = threads_rule(cfg)
    counts = list(range(1, cores() + 1))
    speeds: dict[tuple[str, int], list[tuple[float, float]]] = {}
    for i in range(args.seeds):
        for load in ("alone", "beside a busy process"):
            for n in counts:
                hog = subprocess.Popen([sys.executable, "-c", HOG]) if load != "alone" else None
                try:
                    s = _run(preset, overrides, n, out / f"round{i}-{'busy' if hog else 'alone'}-threads{n}")
                finally:
                    if hog is not None:
                        hog.kill()
                        hog.wait()
                speeds.setdefault((load, n), []).append((s["env_steps_per_s"], s["updates_per_s"]))
                print(f"  round {i + 1}, {load}, {n} thread(s): {s['env_steps_per_s']:.0f} env steps/s, "
                      f"{s['updates_per_s']:.0f} updates/s", file=sys.stderr, flush=True)
    lines = [f"`rlpipe train {preset} {' '.join(overrides)}` on {cores()} cores, median of {args.seeds} rounds; "
             f"num_threads=-1 chooses {rule} here ({why})", "",
             "| machine | learner threads | env steps/s | updates/s |", "|---|---|---|---|"]
    rows = []
    for (load, n), values in speeds.items():
        env_steps, updates = (statistics.median(v[k] for v in values) for k in (0, 1))
        mark = " (the rule's)" if n == rule else ""
        lines.append(f"| {load} | {n}{mark} | {env_steps:.0f} | {updates:.0f} |")
        rows.append({"machine": load, "threads": n, "env_steps_per_s": env_steps, "updates_per_s": updates,
                     "rounds": [list(v) for v in values]})
    return {"table": "\n".join(lines), "preset": preset, "overrides": overrides, "rule": rule, "why": why, "rows": rows}
