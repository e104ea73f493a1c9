"""The PyBullet adapter: the only module of room-pipeline that imports :mod:`pybullet`
(tests/test_import_layers.py asserts it).

It holds one PyBullet DIRECT world per :class:`ScopeSim` (the scope multibody and the airway wall) and
:func:`press_capsule` (one capsule pressed on a floor: the contact-law probe's world).  What is
simulated, and how a sequence is driven, is the domain's: :mod:`~room_pipeline.robot.simulation`
(the run loop), :mod:`~room_pipeline.robot.probes` (contact, friction and free-settling checks),
:mod:`~room_pipeline.robot.sim_params`, :mod:`~room_pipeline.robot.route`, :mod:`~room_pipeline.robot.wall`.
Poses cross this boundary as 4x4 matrices (SI units), never as PyBullet quaternions.

Scope model
    The bending segment (length ``geometry.l``) is a chain of ``n_links`` rigid capsules
    (diameter ``scope_diameter_mm``; default 5.0 mm, the Ambu aScope 4 Regular) joined at
    the polygon vertices ``s_i = i l / n`` by **two revolute joints** (about the link's x,
    the bending axis, and y, out of plane).  The chain's base is the bending-segment base,
    rolled by ``q2`` (the whole scope rotates), so the nominal constant-curvature shape of
    :mod:`~room_pipeline.robot.kinematics` is ``theta_x = kappa(q1) l / n`` at every inner
    vertex and ``kappa l / (2 n)`` at the base (the polygon's vertices then lie on the arc;
    its chords are ``l/n`` long, a relative length error ``(kappa l/n)^2 / 24``), ``theta_y = 0``.
    The tip camera sits at the last vertex; its view direction is the last chord turned by
    half the last vertex's actual joint angles (the discrete tangent there).
    Every joint is a spring-damper about its target (``joint_stiffness``, ``joint_damping``),
    applied as a torque each step (motors off: velocity control with force 0).  Default
    (``joint_integration: implicit``): stable PD (Tan, Liu & Turk 2011): the spring acts at
    ``theta + dt*omega`` and the damper at the velocity predicted with the joint-space mass
    matrix, so the stiff, light chain is stable at a 5 ms step.  ``explicit``:
    ``tau = k (theta* - theta) - c dtheta/dt`` with raised link inertia (``inertia_factor``).  ``motor`` (not
    the default: benchmarks/results/simulation_motor_law.md): each joint is a velocity motor, a constraint row
    solved with the contacts in Bullet's LCP (target velocity, impulse <= force x dt), aiming at the massless
    spring-damper's velocity ``k e / (d + k dt)``, its torque capped at ``|k e| + d |omega|``: a joint the wall
    holds presses with its whole spring at any step.
    The stable PD's torque is ``M (M + dt D)^-1 (k e - D omega)``: the spring's ``k e`` in free motion,
    but where the wall holds a joint still only the share ``M (M + dt D)^-1`` of it (its prediction
    does not know the contact), a share that grows with ``M / (dt D)``: a resting contact presses
    harder at a smaller step or a larger mass (physical mass: the 1 ms run about half the 0.5 ms
    run's force; mass x10 at 5 ms has the 0.5 ms run's ``M / (dt D)``;
    benchmarks/results/simulation_contact_candidates.md).

Contact
    Soft normal contact ``f = k_n delta + c_n d(delta)/dt`` via
    ``changeDynamics(contactStiffness=k_n, contactDamping=c_n)`` **on the scope's links only**
    (set on both bodies the two springs act in series and the penetration doubles).
    Bullet leaves ``contact_slop_mm`` of penetration uncorrected (its own 0.01 mm by default), so the
    law reads ``delta = f / k_n + slop`` (0.260 mm at 1 N); ``contact_slop_mm: 0`` makes it exact.
    ``solver_residual_threshold`` (Bullet's 1e-7) ends the solver's iterations early once the squared
    impulse change falls below it.
    Coulomb friction: Bullet has one coefficient per pair, the *product* of the two bodies'
    ``lateralFriction``; the wall carries 1.0 and each scope link ``mu``.  With
    ``friction_model: switch`` a link's ``mu`` is ``mu_s`` while its speed is below
    ``slip_speed_mm_s`` and ``mu_d`` while it slides (re-evaluated every frame); with
    ``dynamic`` it is always ``mu_d`` (slightly more slip than the static law allows).

Airway
    A static concave triangle mesh (``GEOM_MESH`` with ``GEOM_FORCE_CONCAVE_TRIMESH``) of the
    lumen surface; the scope is inside it (triangle contacts are two-sided, so the wall
    pushes the scope back into the lumen).  Its Bullet collision margin is ``wall_margin_mm``
    (default 0): Bullet's own default (1 mm) inflates every triangle by the margin, i.e. the
    lumen was 1 mm narrower than the mesh (a capsule rests 1 mm above a triangle floor), and
    the margin also enlarges every triangle query, doubling the step time deep in a narrow
    branch (benchmarks/results/simulation.md).  Only the wall near the route is loaded
    (``collision_corridor_mm``): every triangle whose bounding sphere reaches within that
    distance of the planned path, extended back by the bending segment and the passive shaft;
    the run records how far inside the corridor the scope's surface stayed
    (``corridor_margin_mm``) and is redone with the corridor doubled if that went negative
    (three times, then the whole mesh).  The wall goes to Bullet in bodies of at most
    ``max_body_faces`` triangles (cut along the route), so no mesh size reaches
    ``createCollisionShape``'s limit (131,708 faces passed, 200,914 failed).  With ``crop_mesh`` only the triangles whose
    centroid is within ``crop_radius_mm`` of the scope are loaded, and the crop is rebuilt
    when any scope point has moved more than ``crop_rebuild_mm`` since the last build.
"""
from __future__ import annotations

import itertools
import math

import numpy as np
import pybullet as p

from ..errors import ConfigError
from ..geometry.rotations import log_so3 as _log_so3
from ..geometry.rotations import mat_to_quat as _mat_to_quat
from ..geometry.rotations import rx as _rx
from ..geometry.rotations import ry as _ry
from .kinematics import ScopeGeometry, kappa
from .sim_params import SimParams
from .wall import split_faces

#: what PyBullet raises when a call fails (the simulation turns it into one ``InputError`` line)
PhysicsError = p.error


def engine_version() -> int:
    """PyBullet's API version (recorded in ``robot_config.json``)."""
    return p.getAPIVersion()


def _quat_to_mat(qt) -> np.ndarray:
    return np.array(p.getMatrixFromQuaternion(qt)).reshape(3, 3)


class ScopeSim:
    """One PyBullet DIRECT world: the scope multibody and (optionally) the airway mesh.

    Args:
        params, geometry: the model.
        n_shaft: passive shaft links behind the bending segment (0: none, the kinematic model).
        shaft_length: their total length, m.
    """

    def __init__(self, params: SimParams, geometry: ScopeGeometry, n_shaft: int = 0, shaft_length: float = 0.0) -> None:
        self.params, self.geometry = params, geometry
        self.cid = p.connect(p.DIRECT)
        c = self.cid
        p.resetSimulation(physicsClientId=c)
        p.setPhysicsEngineParameter(fixedTimeStep=params.time_step_s, numSolverIterations=params.solver_iterations,
                                    numSubSteps=0, deterministicOverlappingPairs=1,
                                    solverResidualThreshold=params.solver_residual_threshold,
                                    contactSlop=params.contact_slop_mm * 1e-3, physicsClientId=c)
        p.setGravity(0.0, 0.0, -params.gravity_m_s2, physicsClientId=c)
        self.radius = 0.5 * params.scope_diameter_mm * 1e-3
        self.n_shaft, self.n_bend = int(n_shaft), params.n_links
        self.ds = geometry.l / params.n_links
        self.ds_shaft = shaft_length / n_shaft if n_shaft else 0.0
        self.wall = -1
        self.wall_shape = -1
        self.wall_faces = 0
        self.walls: list[int] = []
        self.max_body_faces = int(params.max_body_faces)
        self._build_scope()

    # ---- construction
    def _build_scope(self) -> None:
        c, prm = self.cid, self.params
        lengths = [self.ds_shaft] * self.n_shaft + [self.ds] * self.n_bend
        masses, shapes, positions, parents, axes, inertias, ipos, k, d = [], [], [], [], [], [], [], [], []
        I_art = prm.inertia_factor * prm.joint_damping * prm.time_step_s
        k_shaft = prm.shaft_bending_stiffness_nm2 / self.ds_shaft if self.n_shaft else 0.0
        d_shaft = k_shaft * prm.joint_damping / prm.joint_stiffness
        I_shaft = prm.inertia_factor * d_shaft * prm.time_step_s
        prev_len = 0.0
        for i, L in enumerate(lengths):
            shaft = i < self.n_shaft
            m = prm.linear_density_kg_m * prm.mass_scale * L
            I_phys = m * (3 * self.radius ** 2 + L ** 2) / 12.0
            I = max(I_phys, I_shaft if shaft else I_art)
            shape = p.createCollisionShape(p.GEOM_CAPSULE, radius=self.radius, height=L,
                                           collisionFramePosition=[0.0, 0.0, 0.5 * L], physicsClientId=c)
            # dummy link carrying the x joint at the vertex, then the capsule on the y joint
            masses += [1e-3 * m, m]
            shapes += [-1, shape]
            positions += [[0.0, 0.0, prev_len], [0.0, 0.0, 0.0]]
            parents += [2 * i if i > 0 else 0, 2 * i + 1]
            axes += [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
            inertias += [[1e-3 * I] * 3, [I] * 3]
            ipos += [[0.0, 0.0, 0.0], [0.0, 0.0, 0.5 * L]]
            kk, dd = (k_shaft, d_shaft) if shaft else (prm.joint_stiffness, prm.joint_damping)
            k += [kk, kk]
            d += [dd, dd]
            prev_len = L
        n = len(masses)
        self.body = p.createMultiBody(
            baseMass=0.0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=-1,
            basePosition=[0.0, 0.0, 0.0], baseOrientation=[0.0, 0.0, 0.0, 1.0],
            linkMasses=masses, linkCollisionShapeIndices=shapes, linkVisualShapeIndices=[-1] * n,
            linkPositions=positions, linkOrientations=[[0.0, 0.0, 0.0, 1.0]] * n,
            linkInertialFramePositions=ipos, linkInertialFrameOrientations=[[0.0, 0.0, 0.0, 1.0]] * n,
            linkParentIndices=parents, linkJointTypes=[p.JOINT_REVOLUTE] * n, linkJointAxis=axes,
            physicsClientId=c)
        self.joints = list(range(n))
        self.capsules = list(range(1, n, 2))
        self.k = np.array(k)
        self.d = np.array(d)
        for j in self.joints:
            p.changeDynamics(self.body, j, localInertiaDiagonal=inertias[j], linearDamping=0.0, angularDamping=0.0,
                             jointDamping=0.0, physicsClientId=c)
        for j in self.capsules:
            p.changeDynamics(self.body, j, contactStiffness=prm.contact_stiffness, contactDamping=prm.contact_damping,
                             lateralFriction=prm.friction_dynamic if prm.friction_model == "dynamic"
                             else prm.friction_static, restitution=0.0, physicsClientId=c)
        self._mu = np.full(len(self.capsules), -1.0)
        p.setJointMotorControlArray(self.body, self.joints, p.VELOCITY_CONTROL, forces=[0.0] * n, physicsClientId=c)
        self.targets = np.zeros(n)
        self._q1_targets = None
        self._bend_pattern = np.zeros(n)          # joint targets per unit vertex angle: half at the base vertex
        self._bend_pattern[2 * self.n_shaft] = 0.5
        self._bend_pattern[2 * self.n_shaft + 2::2] = 1.0
        self._phi_per_q1 = float(kappa(1.0, self.geometry)) * self.ds     # vertex angle per unit q1 (kappa is linear)
        self.base_pose = np.eye(4)
        self.implicit = prm.joint_integration == "implicit"
        self.motor = prm.joint_integration == "motor"
        self.dt = prm.time_step_s
        self._pd_gain = None
        self._D_joint = np.diag(self.d)
        self._since_mass = 0

    def close(self) -> None:
        if self.cid is not None and self.cid >= 0:
            p.disconnect(physicsClientId=self.cid)
            self.cid = -1

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            if getattr(self, "cid", -1) >= 0 and p.isConnected(self.cid):
                p.disconnect(physicsClientId=self.cid)
        except Exception:
            pass

    # ---- airway
    def set_wall(self, vertices: np.ndarray, faces: np.ndarray, order: np.ndarray | None = None) -> None:
        """Replace the static airway mesh (concave triangle meshes, two-sided contacts).

        Any size: the faces go to Bullet in bodies of at most ``max_body_faces`` each
        (``createCollisionShape`` fails above ~131k-200k faces, ../shared/DESIGN.md), cut
        in ``order`` (face indices, e.g. sorted along the route) or, by default, along the
        mesh's longest extent, so each body is one compact piece of the wall.
        """
        c = self.cid
        for b in self.walls:
            p.removeBody(b, physicsClientId=c)
        self.walls = []
        self.wall = -1
        self.wall_shape = -1   # (Bullet refuses to remove a shape still referenced; it is freed with the world)
        self.wall_faces = 0
        self.add_wall(vertices, faces, order)

    def add_wall(self, vertices: np.ndarray, faces: np.ndarray, order: np.ndarray | None = None) -> None:
        """Add static wall bodies (as :meth:`set_wall`) after those already loaded."""
        c = self.cid
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        vertices = np.asarray(vertices, float)
        self.wall_faces += int(len(faces))
        if len(faces) == 0:
            return
        for part in split_faces(vertices, faces, self.max_body_faces, order):
            F = faces[part]
            used, inv = np.unique(F.ravel(), return_inverse=True)
            try:
                shape = p.createCollisionShape(p.GEOM_MESH, vertices=vertices[used].tolist(),
                                               indices=inv.astype(np.int64).tolist(),
                                               flags=p.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=c)
            except p.error:
                shape = -1
            if shape < 0:
                raise ConfigError(f"PyBullet refused a wall body of {len(F)} faces "
                                  f"(simulate.max_body_faces = {self.max_body_faces}); lower it")
            body = p.createMultiBody(0.0, shape, -1, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], physicsClientId=c)
            p.changeDynamics(body, -1, lateralFriction=1.0, restitution=0.0,
                             collisionMargin=self.params.wall_margin_mm * 1e-3, physicsClientId=c)
            self.walls.append(body)
        self.wall, self.wall_shape = self.walls[0], -1

    def add_box(self, half_extents, position) -> int:
        """A static box (contact-law checks); friction 1.0 so the pair's coefficient is the scope's."""
        c = self.cid
        shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(half_extents), physicsClientId=c)
        b = p.createMultiBody(0.0, shape, -1, list(position), [0.0, 0.0, 0.0, 1.0], physicsClientId=c)
        p.changeDynamics(b, -1, lateralFriction=1.0, restitution=0.0, physicsClientId=c)
        self.wall = b
        self.walls = [b]
        return b

    # ---- state
    def set_base(self, pose: np.ndarray, prev_pose: np.ndarray | None = None, h: float = 0.0,
                 reset: bool = True) -> None:
        """Place the (fixed) base at ``pose``; with ``prev_pose`` and ``h`` also give it the velocity
        that moved it from ``prev_pose`` in ``h`` seconds (linear and angular, world frame).

        ``resetBasePositionAndOrientation`` zeroes the base velocity (joint velocities are kept), so
        without the velocity every link of a scope inserted at 5 mm/s reads 0 mm/s: the contact
        solver sees no slip along the shaft and the friction switch always reads static.
        The step integrates the base by that velocity, so it is placed at ``prev_pose`` and reaches
        ``pose`` at the end of the next step.  ``reset=False`` (with ``prev_pose``): only the velocity
        is set, the base being where the last step took it (Bullet integrates the fixed base too;
        its error over a 10 Hz frame is second order, |v| |w| h^2 per step, and the caller re-places
        it each frame); ``resetBasePositionAndOrientation`` costs more than a contact step.
        """
        self.base_pose = pose
        c = self.cid
        at = pose if prev_pose is None or h <= 0.0 else prev_pose
        if reset or at is pose:
            p.resetBasePositionAndOrientation(self.body, at[:3, 3].tolist(), _mat_to_quat(at[:3, :3]),
                                              physicsClientId=c)
        if at is not pose:
            v = (pose[:3, 3] - prev_pose[:3, 3]) / h
            w = _log_so3(pose[:3, :3] @ prev_pose[:3, :3].T) / h
            p.resetBaseVelocity(self.body, v.tolist(), w.tolist(), physicsClientId=c)

    def set_base_velocity(self, pose: np.ndarray, v, w) -> None:
        """:meth:`set_base` with ``reset=False`` and the velocity already known (``v``, ``w``: lists, world
        frame): the base is where the last step took it; ``pose`` is where this step takes it."""
        self.base_pose = pose
        p.resetBaseVelocity(self.body, v, w, physicsClientId=self.cid)

    def set_bend(self, q1: float) -> None:
        """Joint targets of the bending segment for tendon differential ``q1`` (in its rolled base)."""
        if q1 == self._q1_targets:
            return
        self._q1_targets = q1
        self.targets = (self._phi_per_q1 * q1) * self._bend_pattern

    def reset_joints(self) -> None:
        """Joints at their targets, at rest."""
        for j in self.joints:
            p.resetJointState(self.body, j, float(self.targets[j]), 0.0, physicsClientId=self.cid)

    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        js = p.getJointStates(self.body, self.joints, physicsClientId=self.cid)
        return np.array([j[0] for j in js]), np.array([j[1] for j in js])

    def step(self, n: int = 1) -> None:
        c, body, joints = self.cid, self.body, self.joints
        nj = len(joints)
        for i in range(n):
            js = p.getJointStates(body, joints, physicsClientId=c)
            th = np.array([j[0] for j in js])
            om = np.array([j[1] for j in js])
            if self.motor:
                e = self.targets - th
                p.setJointMotorControlArray(body, joints, p.VELOCITY_CONTROL,
                                            targetVelocities=(self.k * e / (self.d + self.k * self.dt)).tolist(),
                                            forces=(np.abs(self.k * e) + self.d * np.abs(om)).tolist(), physicsClientId=c)
                p.stepSimulation(physicsClientId=c)
                continue
            if self.implicit:
                # stable PD (Tan, Liu & Turk 2011): spring at theta + dt*omega, damper at the predicted
                # velocity omega + dt*acc, acc = (M + dt D)^-1 (e - D omega) from the joint-space mass
                # matrix (bias and contact ignored), i.e. tau = e - D (omega + dt acc) = M (M + dt D)^-1 (e - D omega):
                # one cached matrix, refreshed every `mass_matrix_every` steps (a LAPACK solve per step cost
                # more than the physics step itself: OpenBLAS thread start-up on tiny matrices).
                # Mass-proportional damping alpha*M (mass_damping_per_s) keeps the mass-scaled chain overdamped.
                if self._pd_gain is None or self._since_mass >= self.params.mass_matrix_every:
                    M = np.fromiter(itertools.chain.from_iterable(
                        p.calculateMassMatrix(body, th.tolist(), physicsClientId=c)), float, nj * nj).reshape(nj, nj)
                    alpha = self.params.mass_damping_per_s
                    D = self._D_joint + alpha * M if alpha else self._D_joint
                    self._pd_gain = M @ np.linalg.inv(M + self.dt * D)
                    self._D = D if alpha else None
                    self._since_mass = 0
                self._since_mass += 1
                r = self.k * (self.targets - th - self.dt * om) - (self.d * om if self._D is None else self._D @ om)
                tau = self._pd_gain @ r
            else:
                tau = self.k * (self.targets - th) - self.d * om
            p.setJointMotorControlArray(body, joints, p.TORQUE_CONTROL, forces=tau.tolist(), physicsClientId=c)
            p.stepSimulation(physicsClientId=c)

    def link_frames(self) -> list[np.ndarray]:
        """World 4x4 frames of the capsule links (at their proximal vertex)."""
        out = []
        for s in p.getLinkStates(self.body, self.capsules, computeForwardKinematics=1, physicsClientId=self.cid):
            T = np.eye(4)
            T[:3, :3] = _quat_to_mat(s[5])
            T[:3, 3] = s[4]
            out.append(T)
        return out

    def tip_pose(self) -> np.ndarray:
        """Tip camera pose (4x4 camera-to-world; OpenCV frame = the kinematic tip frame)."""
        s = p.getLinkState(self.body, self.capsules[-1], computeForwardKinematics=1, physicsClientId=self.cid)
        R = _quat_to_mat(s[5])
        last = len(self.joints) - 2
        a = p.getJointStates(self.body, [last, last + 1], physicsClientId=self.cid)
        T = np.eye(4)
        T[:3, 3] = np.array(s[4]) + self.ds * R[:, 2]
        T[:3, :3] = R @ _rx(0.5 * a[0][0]) @ _ry(0.5 * a[1][0])
        return T

    def bend_base_pose(self) -> np.ndarray:
        """World pose of the bending-segment base (rolled by q2): the first bending vertex's parent frame."""
        if self.n_shaft == 0:
            return self.base_pose.copy()
        s = p.getLinkState(self.body, 2 * self.n_shaft - 1, computeForwardKinematics=1, physicsClientId=self.cid)
        T = np.eye(4)
        T[:3, :3] = _quat_to_mat(s[5])
        T[:3, 3] = np.array(s[4]) + self.ds_shaft * T[:3, 2]
        return T

    def sample_points(self) -> np.ndarray:
        """Scope backbone points (every vertex and the tip), world, m."""
        F = self.link_frames()
        pts = [T[:3, 3] for T in F]
        pts.append(F[-1][:3, 3] + self.ds * F[-1][:3, 2])
        return np.array(pts)

    def contacts(self) -> tuple[float, float]:
        """(sum of normal forces N, max penetration m) between the scope and the wall."""
        cps = [cp for w in self.walls for cp in p.getContactPoints(self.body, w, physicsClientId=self.cid)]
        if not cps:
            return 0.0, 0.0
        f = float(sum(cp[9] for cp in cps))
        pen = float(max(0.0, max(-cp[8] for cp in cps)))
        return f, pen

    def contact_points(self) -> list[tuple[int, float, float, np.ndarray]]:
        """Every scope-wall contact point: (link index, penetration m (< 0: a gap), normal force N, contact normal on
        the wall, world)."""
        return [(int(cp[3]), float(-cp[8]), float(cp[9]), np.array(cp[7]))
                for w in self.walls for cp in p.getContactPoints(self.body, w, physicsClientId=self.cid)]

    def update_friction(self) -> None:
        """friction_model 'switch': mu_s for links slower than slip_speed_mm_s, mu_d for the others."""
        prm = self.params
        if prm.friction_model != "switch":
            return
        states = p.getLinkStates(self.body, self.capsules, computeLinkVelocity=1, physicsClientId=self.cid)
        v_base = 0.0
        for i, s in enumerate(states):
            speed = float(np.linalg.norm(s[6])) - v_base
            mu = prm.friction_dynamic if speed > prm.slip_speed_mm_s * 1e-3 else prm.friction_static
            if mu != self._mu[i]:
                p.changeDynamics(self.body, self.capsules[i], lateralFriction=mu, physicsClientId=self.cid)
                self._mu[i] = mu

    def energy(self) -> float:
        """Kinetic energy of the links plus the joint springs' potential energy, J."""
        c = self.cid
        e = 0.0
        states = p.getLinkStates(self.body, self.joints, computeLinkVelocity=1, computeForwardKinematics=1,
                                 physicsClientId=c)
        for j, s in enumerate(states):
            info = p.getDynamicsInfo(self.body, j, physicsClientId=c)
            m, I = info[0], np.array(info[2])
            v, w = np.array(s[6]), np.array(s[7])
            R = _quat_to_mat(s[1])
            wl = R.T @ w
            e += 0.5 * m * float(v @ v) + 0.5 * float(wl @ (I * wl))
        th, _ = self.joint_state()
        e += 0.5 * float(np.sum(self.k * (th - self.targets) ** 2))
        return e

    # ---- probes (robot/probes.py)
    def push_links(self, force_n: float) -> None:
        """Apply ``force_n`` N along world -z at every capsule link's origin (for the next step)."""
        for j in self.capsules:
            pos = p.getLinkState(self.body, j, computeForwardKinematics=1, physicsClientId=self.cid)[0]
            p.applyExternalForce(self.body, j, [0.0, 0.0, -force_n], pos, p.WORLD_FRAME, physicsClientId=self.cid)

    def wall_contacts(self) -> list[tuple[float, np.ndarray]]:
        """(normal force N, friction force vector N, world) of each contact point with ``self.wall``."""
        return [(cp[9], cp[10] * np.array(cp[11]) + cp[12] * np.array(cp[13]))
                for cp in p.getContactPoints(self.body, self.wall, physicsClientId=self.cid)]

    def link_velocities(self) -> list:
        """World linear velocity (m/s, 3-tuple) of every capsule link."""
        states = p.getLinkStates(self.body, self.capsules, computeLinkVelocity=1, physicsClientId=self.cid)
        return [s[6] for s in states]


def press_capsule(time_step_s: float, solver_iterations: int, wall_margin_m: float, radius: float, length: float,
                  mass: float, contact_stiffness: float, contact_damping: float, friction: float, force_n: float,
                  steps: int, solver_residual_threshold: float = 1e-7, contact_slop_m: float = 1e-5) -> tuple[float, float]:
    """One free capsule (``radius``, ``length``, ``mass``; soft contact on it alone) lying along world y
    on a triangle-mesh floor at z = 0 (concave trimesh, friction 1.0, collision margin ``wall_margin_m``),
    no gravity, pushed down by ``force_n`` N at its centre for ``steps`` steps.

    Returns (height of its centre, m; sum of the contact normal forces, N).  Its own DIRECT world,
    disconnected on return.
    """
    c = p.connect(p.DIRECT)
    try:
        p.setPhysicsEngineParameter(fixedTimeStep=time_step_s, numSolverIterations=solver_iterations,
                                    numSubSteps=0, deterministicOverlappingPairs=1,
                                    solverResidualThreshold=solver_residual_threshold, contactSlop=contact_slop_m,
                                    physicsClientId=c)
        p.setGravity(0.0, 0.0, 0.0, physicsClientId=c)
        floor = p.createCollisionShape(p.GEOM_MESH, vertices=[[-0.05, -0.05, 0.0], [0.05, -0.05, 0.0],
                                                              [0.05, 0.05, 0.0], [-0.05, 0.05, 0.0]],
                                       indices=[0, 1, 2, 0, 2, 3], flags=p.GEOM_FORCE_CONCAVE_TRIMESH,
                                       physicsClientId=c)
        b = p.createMultiBody(0.0, floor, -1, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], physicsClientId=c)
        p.changeDynamics(b, -1, lateralFriction=1.0, restitution=0.0, collisionMargin=wall_margin_m,
                         physicsClientId=c)
        cap = p.createCollisionShape(p.GEOM_CAPSULE, radius=radius, height=length, physicsClientId=c)
        s = p.createMultiBody(mass, cap, -1, [0.0, 0.0, radius],
                              p.getQuaternionFromEuler([0.5 * math.pi, 0.0, 0.0]), physicsClientId=c)
        p.changeDynamics(s, -1, contactStiffness=contact_stiffness, contactDamping=contact_damping,
                         lateralFriction=friction, restitution=0.0, linearDamping=0.0,
                         angularDamping=0.0, physicsClientId=c)
        for _ in range(steps):
            pos = p.getBasePositionAndOrientation(s, physicsClientId=c)[0]
            p.applyExternalForce(s, -1, [0.0, 0.0, -force_n], pos, p.WORLD_FRAME, physicsClientId=c)
            p.stepSimulation(physicsClientId=c)
        z = p.getBasePositionAndOrientation(s, physicsClientId=c)[0][2]
        fn = sum(cp[9] for cp in p.getContactPoints(s, b, physicsClientId=c))
        return z, float(fn)
    finally:
        p.disconnect(physicsClientId=c)
