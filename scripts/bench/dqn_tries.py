"""The ``dqn`` preset's training speed under config variants, each against the plain-PyTorch loop in the same process.

    python -m rlpipe.scripts.bench.dqn_tries [--rounds 3] [--iterations 6000] [--variant NAME=OVERRIDES ...]

Each round times the plain loop on its best thread setting (``dqn.plain_dqn_best_threads``) and then one
``rlpipe train dqn`` per variant (in this process, evaluations off; the run's own ``updates_per_s``,
training time only), so each ratio compares two figures taken seconds apart under the same load.
Prints a Markdown table of the rounds' median ratios (the target: a ratio of at least 1).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

from rlpipe.scripts.bench.dqn import plain_dqn_best_threads

VARIANTS = {
    "preset": [],
    "collector process": ["collector.sync=false"],
}


def main(argv: list[str] | None = None) -> int:
    from rlpipe.pipelines import pipeline_class, resolve_preset
    from rlpipe.pipelines.config import apply_overrides

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=6000)
    parser.add_argument("--peer-iterations", type=int, default=3000)
    parser.add_argument("--preset", default="dqn")
    parser.add_argument("--variant", action="append", default=[], metavar="NAME=KEY=VALUE,...",
                        help="a variant: its name, '=', then comma-separated overrides (default: preset, collector process)")
    args = parser.parse_args(argv)
    variants = dict(VARIANTS)
    if args.variant:
        variants = {}
        for v in args.variant:
            name, _, overrides = v.partition("=")
            variants[name] = [o for o in overrides.split(",") if o]
    out = Path(tempfile.mkdtemp(prefix="rlpipe-dqn-tries-"))
    ratios: dict[str, list[float]] = {name: [] for name in variants}
    speeds: dict[str, list[float]] = {name: [] for name in variants}
    peers = []
    for r in range(args.rounds):
        peer, _ = plain_dqn_best_threads(args.peer_iterations, seed=r)
        peers.append(peer)
        for name, overrides in variants.items():
            algo, cfg = resolve_preset(args.preset)
            cfg = apply_overrides(cfg, ["eval_interval=0", "num_eval_episodes=1", "log_interval=1000",
                                        "checkpoint_interval=100000000", "policy_save_interval=100000000",
                                        f"num_iterations={args.iterations}", f"seed={r}", *overrides])
            result = pipeline_class(algo)(cfg).train(out / f"{r}-{len(speeds[name])}-{name.replace(' ', '_')}",
                                                     progress=False)
            speed = result.summary["updates_per_s"]
            speeds[name].append(speed)
            ratios[name].append(speed / peer)
            print(f"  round {r}: plain {peer:.0f} it/s; {name}: {speed:.0f} it/s, ratio {speed / peer:.2f}", file=sys.stderr)
    rows = [f"| {name} | `{' '.join(variants[name]) or '(none)'}` | {', '.join(f'{s:.0f}' for s in speeds[name])} | "
            f"{', '.join(f'{x:.2f}' for x in ratios[name])} | **{statistics.median(ratios[name]):.2f}** |"
            for name in variants]
    print("\n".join([
        f"`{args.preset}` preset, {args.iterations} iterations per run, against the plain-PyTorch loop "
        f"({args.peer_iterations} iterations) in the same process, {args.rounds} rounds; plain loop: "
        f"{', '.join(f'{p:.0f}' for p in peers)} it/s",
        "",
        "| variant | overrides | rlpipe it/s, each round | ratio to the plain loop, each round | median ratio |",
        "|---|---|---|---|---|",
        *rows,
    ]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
