"""``rlpipe bench gpu``: the update and whole training runs on a CUDA device, eager against CUDA graphs.

Two tables, both on the machine's first GPU, each row in the same run:

1. The update alone (``pipeline.update_step`` on a fixed batch already on the device, the median
   over chunks, synchronised at chunk ends): eager; replayed as CUDA graphs (``cudagraph=true``,
   ``pipelines/training/update_graph.py``); compiled and replayed (``compile=true``). CleanRL's settings:
   SAC and TD3 with 256x256 networks at batch 256 on HalfCheetah-v5, DQN 120-84 at batch 128.
2. Whole training runs as a user starts them (``rlpipe train ... device=cuda``, a fresh process per
   run): env steps/s with one update per env step, the env stepped on the CPU in the learner's process
   (in-process collector), as CleanRL and LeanRL do, so the figure compares with LeanRL's published
   H100 figures for HalfCheetah (TD3 936, SAC 725 env steps/s). Three ways to run that loop, each a row:
   a block of 1 env step then 1 update (LeanRL's interleave; the policy on the GPU, a host-device round
   trip per step); blocks of 32 env steps then their 32 updates (the loop's per-block work, the
   block's copy to the GPU, the replay write and the divergence check, paid once per 32 steps); the
   same with the collect policy acting from a CPU copy (``collector.policy_device=cpu``, weights copied
   after each block's updates: no round trip per step); the same blocks from one collector process
   (``collector.sync=false``: TorchRL's ``MultiAsyncCollector``, the worker collecting the next block from
   its CPU copy while the learner makes this block's updates, its blocks stored on the CPU and copied to
   the GPU by the learner). ``--modes`` picks among them (step, blocks, cpu-copy, process). The rate is
   the in-run one (log rows after learning starts; start-up and compilation left out). LeanRL does not
   run here (no peer venv on the GPU machine): its figures are quoted, not a ratio measured in this run.
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
TRAIN_COMMON = ["device=cuda", "compile=true", "collector.workers=1", "collector.sync=true", "eval_interval=0",
                "num_eval_episodes=1", "initial_eval=false", "baseline_episodes=0", "checkpoint_interval=1000000",
                "policy_save_interval=1000000", "log_interval=1000", "replay_buffer_capacity=1000000"]
TRAIN_MODES = [
    ("step", "1 step, 1 update; policy on the GPU", ["collector.frames_per_batch=1"]),
    ("blocks", "blocks of 32; policy on the GPU", ["collector.frames_per_batch=32"]),
    ("cpu-copy", "blocks of 32; policy on a CPU copy", ["collector.frames_per_batch=32", "collector.policy_device=cpu"]),
    ("process", "blocks of 32 from a collector process, overlapping the updates; policy on its CPU copy",
     ["collector.frames_per_batch=32", "collector.policy_device=cpu", "collector.sync=false"]),
]
"""(``--modes`` key, column, overrides) of the training table"""


def bench_gpu(args, out: Path) -> dict:
    from rlpipe.pipelines import pipeline_class, resolve_preset
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.pipelines.errors import InputError
    from rlpipe.scripts.bench.cleanrl import in_run_updates_per_s, timed_train
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
    steps = args.steps or 6000
    cells: dict[tuple[str, str], float | None] = {}
    cases = TRAIN_CASES if "training" in args.parts else []
    # the collector process and the CPU copy first, then the per-step loop: a command cut short by its time
    # limit keeps the main figures
    modes = [m for m in (3, 2, 0, 1) if TRAIN_MODES[m][0] in (args.modes or [k for k, _, _ in TRAIN_MODES])]
    for m in modes:
        _, mode, flags = TRAIN_MODES[m]
        for preset, overrides, label in cases:
            run_dir = out / f"{preset}-mode{m}"
            cells[label, mode] = None
            try:
                run = timed_train(preset, [*TRAIN_COMMON, *overrides, *flags, f"num_iterations={steps}",
                                           f"seed={args.seed}", *args.overrides], run_dir)
            except RuntimeError as exc:  # one mode failing leaves the others' figures
                print(f"[bench gpu] {label} training, {mode}: failed: {exc}", file=sys.stderr, flush=True)
                continue
            cells[label, mode] = rate = in_run_updates_per_s(run_dir / "metrics.csv")
            figures["training"].append({"case": label, "mode": mode, "updates_per_s_in_run": rate,
                                        "wall_s": run["wall_s"], "command": run["command"]})
            print(f"[bench gpu] {label} training, {mode}: {rate or 0:.0f} env steps/s with one update each, in the run "
                  f"({run['wall_s']:.0f} s from launch)", file=sys.stderr, flush=True)
    columns = [TRAIN_MODES[m][1] for m in sorted(modes)]
    train_rows = [f"| {label}, HalfCheetah-v5 | " + " | ".join(
        f"{cells[label, mode]:.0f}" if cells.get((label, mode)) else "-" for mode in columns) + " |"
        for _, _, label in cases]
    table = "\n".join([
        f"GPU: {name} (torch {torch.__version__}); every row measured in this run.",
        "",
        "| update | eager | CUDA graphs | compiled + CUDA graphs | best against eager |",
        "|---|---|---|---|---|",
        *rows,
        "",
        "Training runs (`rlpipe train ... device=cuda compile=true`, one update per env step, env on the CPU in the "
        "learner's process): env steps/s (= updates/s) inside the run, from its log rows after learning starts.",
        "",
        "| run | " + " | ".join(columns) + " |",
        "|---|" + "---|" * len(columns),
        *train_rows,
    ])
    return {**figures, "table": table}
