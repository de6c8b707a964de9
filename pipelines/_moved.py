"""Old import paths of modules that moved (kept for one release), for ``rlpipe.pipelines`` and ``rlpipe.scripts``.

``import rlpipe.pipelines.loop`` (or ``from rlpipe.pipelines import checkpoint``, or
``rlpipe.scripts.bench_collect``) still works, gives the module at its new place, and warns once with a
``DeprecationWarning`` naming that place. Delete this module, ``scripts/_moved.py`` and their lines in the
two packages' ``__init__`` in the release after 0.2.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

# old module (under rlpipe.pipelines) -> its place now
MOVED = {
    "loop": "training.loop",
    "triggers": "training.triggers",
    "state": "training.state",
    "rate_limiter": "training.rate_limiter",
    "meters": "training.meters",
    "update_graph": "training.update_graph",
    "supervision": "workers.supervision",
    "evaluation": "workers.evaluation",
    "ray_backend": "workers.ray",
    "ray_eval": "workers.ray_eval",
    "rundir": "artifacts.rundir",
    "checkpoint": "artifacts.checkpoint",
    "export": "artifacts.export",
    "files": "artifacts.files",
    "video": "artifacts.video",
    "runtime": "system.runtime",
    "memory": "system.memory",
}


class MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``PACKAGE.<old>[.sub]`` and hands back the module at its new place (a moved package's
    submodules follow it)."""

    def __init__(self, package: str, moved: dict[str, str]):
        self.package, self.moved = package, moved

    def _new_name(self, fullname: str) -> str | None:
        if not fullname.startswith(self.package + "."):
            return None
        first, dot, rest = fullname[len(self.package) + 1:].partition(".")
        if first not in self.moved:
            return None
        return f"{self.package}.{self.moved[first]}{dot}{rest}"

    def find_spec(self, fullname, path=None, target=None):
        new = self._new_name(fullname)
        if new is None:
            return None
        # the new file as origin: ``python -m`` of an old path gives it to the module as sys.argv[0]
        return importlib.util.spec_from_loader(fullname, self, origin=importlib.util.find_spec(new).origin)

    def create_module(self, spec):
        new = self._new_name(spec.name)
        warnings.warn(f"{spec.name} moved to {new}; the old path goes in the next release", DeprecationWarning,
                      stacklevel=2)
        return importlib.import_module(new)

    def exec_module(self, module):  # the module is the new one, already executed
        pass

    def get_code(self, fullname):
        """The new module's code, for ``python -m`` of an old path (runpy asks for it)."""
        new = self._new_name(fullname)
        warnings.warn(f"{fullname} moved to {new}: run python -m {new}; the old path goes in the next release",
                      FutureWarning, stacklevel=2)  # FutureWarning: shown to a command-line user
        return importlib.util.find_spec(new).loader.get_code(new)


def install(package: str = "rlpipe.pipelines", moved: dict[str, str] = MOVED) -> None:
    """Put the finder for ``package``'s moved modules first on the import path (a moved package's new
    folder would otherwise be found again under its old name by the path finder)."""
    if not any(isinstance(f, MovedModules) and f.package == package for f in sys.meta_path):
        sys.meta_path.insert(0, MovedModules(package, moved))
