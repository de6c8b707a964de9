"""Old import paths of modules that moved into the rooms of ``pipelines/`` (kept for one release).

``import rlpipe.pipelines.loop`` (or ``from rlpipe.pipelines import checkpoint``) still works, gives the
module at its new place, and warns once with a ``DeprecationWarning`` naming that place. Delete this
module and its line in ``pipelines/__init__.py`` in the release after 0.2.
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
_PACKAGE = "rlpipe.pipelines"


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``rlpipe.pipelines.<old>`` and hands back the module at its new place."""

    def find_spec(self, fullname, path=None, target=None):
        package, _, name = fullname.rpartition(".")
        if package != _PACKAGE or name not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        new = f"{_PACKAGE}.{MOVED[spec.name.rpartition('.')[2]]}"
        warnings.warn(f"{spec.name} moved to {new}; the old path goes in the next release", DeprecationWarning,
                      stacklevel=2)
        return importlib.import_module(new)

    def exec_module(self, module):  # the module is the new one, already executed
        pass


def install() -> None:
    if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
        sys.meta_path.append(_MovedModules())
