"""gymnasium-robotics 1.4.2 under MuJoCo 4: its joint helpers compare ``model.jnt_type[i]`` (a NumPy int32)
with ``mujoco.mjtJoint`` members, which MuJoCo 4's enums no longer equal, so every Fetch env fails its
first reset with an ``AssertionError``. ``apply`` gives those helpers a view of ``mujoco`` whose
``mjtJoint`` members are plain ints. Delete this module once gymnasium-robotics compares them itself
(a release after 1.4.2) or MuJoCo's enums equal NumPy ints again.
"""

from __future__ import annotations

import types

__all__ = ["apply"]


class _MujocoWithIntJoints(types.ModuleType):
    def __init__(self, mujoco):
        super().__init__("mujoco")
        self._mujoco = mujoco
        self.mjtJoint = types.SimpleNamespace(**{name: int(getattr(mujoco.mjtJoint, name))
                                                 for name in dir(mujoco.mjtJoint) if name.startswith("mjJNT_")})

    def __getattr__(self, name):
        return getattr(self._mujoco, name)


def apply() -> None:
    import mujoco
    import numpy as np
    from gymnasium_robotics.utils import mujoco_utils

    if isinstance(mujoco_utils.mujoco, _MujocoWithIntJoints):
        return
    if np.int32(int(mujoco.mjtJoint.mjJNT_SLIDE)) in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
        return  # the versions agree: nothing to mend
    mujoco_utils.mujoco = _MujocoWithIntJoints(mujoco)
