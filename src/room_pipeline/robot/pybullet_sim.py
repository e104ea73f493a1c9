"""The names ``robot/pybullet_sim.py`` held before it was split (kept so code written against it runs).

The module was the PyBullet adapter and the simulation in one file; it is now
:mod:`~room_pipeline.robot.pybullet_adapter` (the only importer of PyBullet: the world, the scope
multibody, the wall bodies), :mod:`~room_pipeline.robot.simulation` (the run loop, :class:`SimResult`,
``robot_config``), :mod:`~room_pipeline.robot.sim_params`, :mod:`~room_pipeline.robot.route`,
:mod:`~room_pipeline.robot.wall`, :mod:`~room_pipeline.robot.probes` and
:mod:`room_pipeline.geometry.rotations`.  New code imports from those; nothing in ``src/`` imports this.
"""
from __future__ import annotations

from ..geometry.rotations import log_so3 as _log_so3  # noqa: F401
from ..geometry.rotations import log_so3_batch  # noqa: F401
from ..geometry.rotations import mat_to_quat as _mat_to_quat  # noqa: F401
from ..geometry.rotations import rx as _rx  # noqa: F401
from ..geometry.rotations import ry as _ry  # noqa: F401
from ..geometry.rotations import rz as _rz  # noqa: F401
from .kinematics import camera_roll, kappa, straight_roll_change  # noqa: F401
from .probes import contact_probe, friction_probe, settle_free  # noqa: F401
from .pybullet_adapter import ScopeSim  # noqa: F401
from .route import Route  # noqa: F401
from .sim_params import FRICTION_MODELS, INSERTION_MODELS, TRACK_MODES, SimParams  # noqa: F401
from .simulation import SimResult, check_inputs, robot_config, simulate  # noqa: F401
from .wall import crop_faces, route_corridor, split_faces  # noqa: F401
