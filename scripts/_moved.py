"""Old import paths of the benchmarks, from before ``scripts/bench/`` was a package (kept for one release).

``import rlpipe.scripts.bench_collect`` (or ``from rlpipe.scripts import bench_profile``, or
``rlpipe.scripts.peers.tfagents``, or ``python -m rlpipe.scripts.bench_minitaur``) still works with a warning
(``rlpipe.pipelines._moved.MovedModules``). Delete this module and its line in ``scripts/__init__.py`` in the
release after 0.2 (``rlpipe.scripts.bench``'s ``__getattr__`` goes with it).
"""

from __future__ import annotations

from rlpipe.pipelines import _moved

# old module or package (under rlpipe.scripts) -> its place now; a moved package's submodules follow it
MOVED = {
    **{f"bench_{name}": f"bench.{name}" for name in (
        "cleanrl", "collect", "dqn_tries", "floor", "gpu", "minitaur", "profile", "ray", "ray_replay", "sac", "td3")},
    "peers": "bench.peers",
}


def install() -> None:
    _moved.install("rlpipe.scripts", MOVED)
