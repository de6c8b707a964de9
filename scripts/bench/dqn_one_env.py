"""DQN with CleanRL's settings and one env in the learner's process against CleanRL's ``dqn.py``,
run with ``python -m``: runs alternated, each side timed as ``rlpipe bench cleanrl`` times it (two lengths
after the random start-up, one torch thread), rlpipe on ``GymCollector`` and, with ``--torchrl``, on TorchRL's
``Collector`` too. Figures: BENCHMARKS.md, "DQN with CleanRL's settings, one env, in-process".
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

IN_PROCESS = ["collector.workers=1", "collector.sync=true", "collector.envs_per_worker=1",
              "collector.frames_per_batch=160", "num_threads=1"]


def rounds(sides: dict, repeats: int, lengths: tuple[int, int] = (5000, 25000), out: Path | None = None,
           label: str = "rlpipe on ") -> None:
    """``repeats`` rounds of CleanRL, then each side of ``sides`` ({name: (extra overrides, hook)}; ``hook(True)``
    before the side's run and ``hook(False)`` after it, or None), each timed as ``rlpipe bench cleanrl`` times it."""
    from rlpipe.scripts.bench.cleanrl import rlpipe_overrides, rlpipe_speed
    from rlpipe.scripts.bench.peers import cleanrl

    out = out or Path(tempfile.mkdtemp(prefix="rlpipe-dqn-one-env-"))
    preset, overrides = rlpipe_overrides("dqn", "CartPole-v1", cleanrl.defaults("dqn"), 0)
    for i in range(repeats):
        peer = cleanrl.cleanrl_speed("dqn", "CartPole-v1", lengths, seed=0, threads=1)
        print(f"round {i + 1} CleanRL, 1 thread: {peer['updates_per_s']:.0f} updates/s "
              f"(in-run {peer.get('updates_per_s_in_run')})", flush=True)
        for name, (extra, hook) in sides.items():
            if hook is not None:
                hook(True)
            r = rlpipe_speed(preset, [*overrides, *IN_PROCESS, *extra], lengths, 10, 0,
                             out / f"{name}-{i}".replace(" ", ""))
            if hook is not None:
                hook(False)
            print(f"round {i + 1} {label}{name}: {r['updates_per_s']:.0f} updates/s "
                  f"(in-run {r['updates_per_s_in_run']:.0f})", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--lengths", nargs=2, type=int, default=[5000, 25000])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--torchrl", action="store_true", help="also time rlpipe on TorchRL's Collector")
    args = parser.parse_args()
    sides = {"GymCollector": (["collector.direct=true"], None)}
    if args.torchrl:
        sides["TorchRL Collector"] = (["collector.direct=false"], None)
    rounds(sides, args.repeats, tuple(args.lengths))


if __name__ == "__main__":
    main()
