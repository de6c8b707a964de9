"""Old import paths of the benchmarks, from before ``scripts/bench/`` was a package (kept for one release).

``import rlpipe.scripts.bench_collect`` (or ``from rlpipe.scripts import bench_profile``, or
``rlpipe.scripts.peers.tfagents``) still works, gives the module at its new place, and warns once with a
``DeprecationWarning`` naming that place. Delete this module and its line in ``scripts/__init__.py`` in the
release after 0.2 (``rlpipe.scripts.bench``'s ``__getattr__`` goes with it).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

# old module or package (under rlpipe.scripts) -> its place now; a moved package's submodules follow it
MOVED = {
    **{f"bench_{name}": f"bench.{name}" for name in (
        "cleanrl", "collect", "dqn_tries", "floor", "gpu", "minitaur", "profile", "ray", "ray_replay", "sac", "td3")},
    "peers": "bench.peers",
}
_PACKAGE = "rlpipe.scripts"


def _new_name(fullname: str) -> str | None:
    if not fullname.startswith(_PACKAGE + "."):
        return None
    first, dot, rest = fullname[len(_PACKAGE) + 1:].partition(".")
    if first not in MOVED:
        return None
    return f"{_PACKAGE}.{MOVED[first]}{dot}{rest}"


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``rlpipe.scripts.<old>[.sub]`` and hands back the module at its new place."""

    def find_spec(self, fullname, path=None, target=None):
        new = _new_name(fullname)
        if new is None:
            return None
        # the new file as origin: ``python -m`` of an old path gives it to the module as sys.argv[0]
        return importlib.util.spec_from_loader(fullname, self, origin=importlib.util.find_spec(new).origin)

    def create_module(self, spec):
        new = _new_name(spec.name)
        warnings.warn(f"{spec.name} moved to {new}; the old path goes in the next release", DeprecationWarning,
                      stacklevel=2)
        return importlib.import_module(new)

    def exec_module(self, module):  # the module is the new one, already executed
        pass

    def get_code(self, fullname):
        """The new module's code, for ``python -m rlpipe.scripts.bench_minitaur`` (runpy asks for it)."""
        new = _new_name(fullname)
        warnings.warn(f"{fullname} moved to {new}: run python -m {new}; the old path goes in the next release",
                      FutureWarning, stacklevel=2)  # FutureWarning: shown to a command-line user
        return importlib.util.find_spec(new).loader.get_code(new)


def install() -> None:
    # First on the path: ``rlpipe.scripts.peers`` is the new package itself, so without this finder in front
    # the path finder would load ``rlpipe.scripts.peers.cleanrl`` from its folder a second time.
    if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
        sys.meta_path.insert(0, _MovedModules())
