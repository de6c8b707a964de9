"""``rlpipe bench gpu``: the update and whole training runs on a CUDA device, eager against CUDA graphs.

Two tables, both on the machine's first GPU, each row in the same run:

1. The update alone (``pipeline.update_step`` on a fixed batch already on the device, the median
   over chunks, synchronised at chunk ends): eager; replayed as CUDA graphs (``cudagraph=true``,
   ``pipelines/training/update_graph.py``); compiled and replayed (``compile=true``). CleanRL's settings:
   SAC and TD3 with 256x256 networks at batch 256 on HalfCheetah-v5, DQN 120-84 at batch 128.
2. Whole training runs as a user starts them (``rlpipe train ... device=cuda``, a fresh process
   per run, two lengths so start-up and compilation cancel): env steps/s with one update per env
   step, the env stepped on the CPU in the learner's process (in-process collector), as CleanRL
   and LeanRL do, so the figure compares with LeanRL's published H100 figures for HalfCheetah
   (TD3 936, SAC 725 env steps/s). LeanRL does not run here (no peer venv on the GPU machine):
   its figures are quoted, not a ratio measured in this run.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

UPDATE_CASES = [
    ("sac-halfcheetah", [], "SAC, HalfCheetah-v5, 256x256, batch 256"),
    ("td3-halfcheetah", ["actor_fc_layer_params=[256,256]", "critic_fc_layer_params=[256,256]", "batch_size=256",
                         "learning_rate=3e-4"], "TD3, HalfCheetah-v5, 256x256, batch 256"),
    ("dqn-cleanrl", [], "DQN, CartPole-v1, 120-84, batch 128"),
]
MODES = [("eager", ["cudagraph=false"]), ("CUDA graphs", ["cudagraph=true"]), ("compiled + CUDA graphs", ["compile=true"])]

# CleanRL's / LeanRL's HalfCheetah settings: one update per env step, 256x256, batch 256 (1k random
# steps here, against their 5k or 10k: only the rate after them is measured)
TRAIN_CASES = [
    ("sac-halfcheetah", ["learning_starts=1000", "initial_collect_steps=1000"], "SAC"),
    ("td3-halfcheetah", UPDATE_CASES[1][1] + ["learning_starts=1000", "initial_collect_steps=1000"], "TD3"),
]
TRAIN_COMMON = ["device=cuda", "collector.workers=1", "collector.sync=true", "collector.frames_per_batch=1",
                "eval_interval=0", "num_eval_episodes=1", "checkpoint_interval=1000000",
                "policy_save_interval=1000000", "log_interval=1000", "replay_buffer_capacity=1000000"]


def bench_gpu(args, out: Path) -> dict:
    from rlpipe.pipelines import pipeline_class, resolve_preset
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.pipelines.errors import InputError
    from rlpipe.scripts.bench.cleanrl import rlpipe_speed
    from rlpipe.scripts.bench.floor import update_seconds

    if not torch.cuda.is_available():
        raise InputError("rlpipe bench gpu: torch sees no CUDA device on this machine; expected a GPU machine")
    name = torch.cuda.get_device_name(0)
    figures: dict = {"device": name, "torch": torch.__version__, "updates": [], "training": []}
    rows = []
    for preset, overrides, label in (UPDATE_CASES if "updates" in args.parts else []):
        algo, cfg = resolve_preset(preset)
        cells = []
        for mode, flags in MODES:
            pipeline = pipeline_class(algo)(apply_overrides(cfg, [*overrides, "device=cuda", *flags, *args.overrides]))
            ms = update_seconds(pipeline, chunks=10, per_chunk=50) * 1e3
            figures["updates"].append({"case": label, "mode": mode, "update_ms": ms})
            print(f"[bench gpu] {label}, {mode}: {ms:.3f} ms per update", file=sys.stderr, flush=True)
            cells.append(ms)
        rows.append(f"| {label} | " + " | ".join(f"{ms:.2f} ms ({1e3 / ms:.0f}/s)" for ms in cells)
                    + f" | {cells[0] / min(cells[1:]):.1f}x |")
    steps = args.steps or 1500
    lengths = tuple(args.lengths) if args.lengths else (steps, 2 * steps)
    train_rows = []
    for preset, overrides, label in (TRAIN_CASES if "training" in args.parts else []):
        cells = []
        for mode, flags in MODES[0:1] + MODES[2:]:
            speed = rlpipe_speed(preset, [*TRAIN_COMMON, *overrides, *flags, *args.overrides], lengths, 1, args.seed,
                                 out / f"{preset}-{mode.replace(' ', '').replace('+', '-')}")
            speed.pop("runs")
            figures["training"].append({"case": label, "mode": mode, **speed})
            print(f"[bench gpu] {label} training, {mode}: {speed['env_steps_per_s']:.0f} env steps/s "
                  f"({speed['updates_per_s_in_run'] or 0:.0f} updates/s in the run)", file=sys.stderr, flush=True)
            cells.append(speed["updates_per_s_in_run"])
        train_rows.append(f"| {label}, HalfCheetah-v5 | " + " | ".join(f"{c or 0:.0f}" for c in cells) + " |")
    table = "\n".join([
        f"GPU: {name} (torch {torch.__version__}); every row measured in this run.",
        "",
        "| update | eager | CUDA graphs | compiled + CUDA graphs | best against eager |",
        "|---|---|---|---|---|",
        *rows,
        "",
        "Training runs (`rlpipe train ... device=cuda`, one update per env step, env on the CPU in the learner's "
        "process): updates/s (= env steps/s) inside the longer run, from its log rows after learning starts.",
        "The two-length rate is in the JSON; with compile=true it is unreliable (compilation time varies between runs).",
        "",
        "| run | eager | compiled + CUDA graphs |",
        "|---|---|---|",
        *train_rows,
    ])
    return {**figures, "table": table}
