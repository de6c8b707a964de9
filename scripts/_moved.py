"""Old import paths of the benchmarks, from before ``scripts/bench/`` was a package (kept for one release).

``import rlpipe.scripts.bench_collect`` (or ``from rlpipe.scripts import bench_profile``, or
``rlpipe.scripts.peers.tfagents``, or ``python -m rlpipe.scripts.bench_minitaur``) still works with a warning
(``rlpipe.pipelines._moved.MovedModules``, loaded when first asked for). Delete this module and its line in
``scripts/__init__.py`` in the release after 0.2 (``rlpipe.scripts.bench``'s ``__getattr__`` goes with it).
"""

from __future__ import annotations

import sys

# old module or package (under rlpipe.scripts) -> its place now; a moved package's submodules follow it
MOVED = {
    **{f"bench_{name}": f"bench.{name}" for name in (
        "cleanrl", "collect", "dqn_tries", "floor", "gpu", "minitaur", "profile", "ray", "ray_replay", "sac", "td3")},
    "peers": "bench.peers",
}


class _MovedLater:
    """A finder (``sys.meta_path``) handing these paths to ``rlpipe.pipelines._moved.MovedModules``, imported when one
    is first asked for: it imports ``rlpipe.pipelines`` (numpy, the configs: a second on a busy machine), which
    ``import rlpipe.scripts`` (the ``rlpipe`` command's first instant, before its ``main`` can answer a Ctrl-C in
    one line) must not wait on."""

    def find_spec(self, fullname, path=None, target=None):
        first = fullname.removeprefix("rlpipe.scripts.").partition(".")[0]
        if not fullname.startswith("rlpipe.scripts.") or first not in MOVED:
            return None
        from rlpipe.pipelines._moved import MovedModules

        return MovedModules("rlpipe.scripts", MOVED).find_spec(fullname, path, target)


def install() -> None:
    if not any(isinstance(f, _MovedLater) for f in sys.meta_path):
        sys.meta_path.insert(0, _MovedLater())
