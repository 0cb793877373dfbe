"""The one documented MyoSuite install, and the one-line errors that name it (imports no MuJoCo itself).

``myo-sim`` 0.2.4 declares ``mujoco<4`` but works with MuJoCo 4; installed with its dependencies it replaces
MuJoCo 4 (packages ``mujoco``, ``mujoco-core``, ``mujoco-studio``) by a 3.x ``mujoco`` and ``import mujoco``
then fails. So it is installed without them, and no extra of this package depends on it.
"""
from __future__ import annotations

MYO_SIM_INSTALL = 'pip install --no-deps "myo-sim==0.2.4"'
MUJOCO_REPAIR = ('pip install --force-reinstall --no-deps "mujoco>=4" "mujoco-core>=4" "mujoco-studio>=4", '
                 f'then add MyoSuite with {MYO_SIM_INSTALL}')


def mujoco_broken_message(err: BaseException) -> str:
    """One line: MuJoCo does not import, why, and the commands that repair it."""
    return f"MuJoCo does not import ({' '.join(str(err).split())}); repair it: {MUJOCO_REPAIR}"


def import_mujoco():
    """``import mujoco``, or one ImportError line naming the repair (e.g. after myo-sim dragged in mujoco<4)."""
    try:
        import mujoco
    except ImportError as err:
        raise ImportError(mujoco_broken_message(err)) from None
    return mujoco
