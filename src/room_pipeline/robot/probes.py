"""Checks of the simulated scope against known loads and the kinematic model: the contact law
(:func:`contact_probe`), Coulomb friction under insertion (:func:`friction_probe`) and the free
scope's settled shape (:func:`settle_free`).  Domain code: the worlds are built through
:mod:`~room_pipeline.robot.pybullet_adapter`."""
from __future__ import annotations

import numpy as np

from ..geometry.rotations import rz as _rz
from .kinematics import ScopeGeometry
from .pybullet_adapter import ScopeSim, press_capsule
from .sim_params import SimParams


def contact_probe(params: SimParams, force_n: float, time_s: float = 1.0) -> tuple[float, float]:
    """Penetration (m) and normal force (N) of one scope link pressed on a static wall by ``force_n``.

    The wall is a triangle-mesh floor built like the airway (concave trimesh, friction 1.0,
    collision margin ``wall_margin_mm``); the link is a free capsule (diameter
    ``scope_diameter_mm``, length ``l / n_links``) with the scope's contact settings (soft
    contact on the link only), lying on it, no gravity; the force acts at its centre for
    ``time_s``.  Penetration is measured against the mesh's true plane (z = 0), so a margin
    that inflates the wall shows up as negative penetration.  The link's mass is the simulated
    one (physical x ``mass_scale``), as in the scope.  The check of the contact law.
    """
    r = 0.5 * params.scope_diameter_mm * 1e-3
    L = 0.05 / params.n_links
    z, fn = press_capsule(params.time_step_s, params.solver_iterations, params.wall_margin_mm * 1e-3, r, L,
                          params.linear_density_kg_m * params.mass_scale * L, params.contact_stiffness,
                          params.contact_damping, params.friction_dynamic, force_n,
                          int(round(time_s / params.time_step_s)), params.solver_residual_threshold,
                          params.contact_slop_mm * 1e-3)
    return r - z, fn


def friction_probe(params: SimParams, geometry: ScopeGeometry, normal_force_n: float, speed_mm_s: float = 5.0,
                   time_s: float = 2.0, by_velocity: bool | None = None) -> dict:
    """Push the straight scope along a flat wall at a known normal load and measure the friction.

    The bending segment lies on a triangle-mesh floor (built like the airway: concave trimesh,
    friction 1.0, margin ``wall_margin_mm``), its axis along world x; ``normal_force_n`` is
    spread evenly over its links (pressing them on the floor), and the base is inserted along
    the axis at ``speed_mm_s`` the way :func:`simulate` moves it (``by_velocity``: default
    ``insertion_by_velocity``), the friction switch re-evaluated every 0.1 s as there.  Over the
    second half of ``time_s``: ``mu`` = |sum of the contacts' friction forces| / sum of their
    normal forces (the pair's coefficient, Bullet's product of the two bodies' ``lateralFriction``),
    ``normal_n`` that sum, ``slip_mm_s`` the links' mean speed along the axis and
    ``dynamic_fraction`` the share of (link, frame) pairs the switch put on ``mu_d``.
    """
    by_velocity = params.insertion_by_velocity if by_velocity is None else bool(by_velocity)
    sim = ScopeSim(params, geometry)
    try:
        sim.set_wall(np.array([[-1.0, -0.5, 0.0], [1.0, -0.5, 0.0], [1.0, 0.5, 0.0], [-1.0, 0.5, 0.0]]),
                     np.array([[0, 1, 2], [0, 2, 3]]))
        base = np.eye(4)
        base[:3, :3] = np.column_stack([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])   # z (axis) = world x
        base[:3, 3] = [0.0, 0.0, sim.radius]
        sim.set_base(base)
        sim.set_bend(0.0)
        sim.reset_joints()
        dt = params.time_step_s
        n = int(round(time_s / dt))
        per_frame = max(1, int(round(0.1 / dt)))
        f_per_link = normal_force_n / len(sim.capsules)
        fric, normal, slip, dyn = np.zeros(3), 0.0, [], []
        for i in range(n):
            if i % per_frame == 0:
                sim.update_friction()
                dyn.extend(np.isclose(sim._mu, params.friction_dynamic) if params.friction_model == "switch"
                           else [True] * len(sim.capsules))
            nxt = sim.base_pose.copy()
            nxt[0, 3] += speed_mm_s * 1e-3 * dt
            sim.set_base(nxt, sim.base_pose if by_velocity else None, dt)
            sim.push_links(f_per_link)
            sim.step(1)
            if i >= n // 2:
                for fn, ff in sim.wall_contacts():
                    normal += fn
                    fric += ff
                slip.append(np.mean([v[0] for v in sim.link_velocities()]))
        m = n - n // 2
        return {"mu": float(np.linalg.norm(fric) / normal) if normal > 0 else 0.0, "normal_n": normal / m,
                "slip_mm_s": float(np.mean(slip)) * 1e3, "dynamic_fraction": float(np.mean(dyn))}
    finally:
        sim.close()


def settle_free(q, params: SimParams, geometry: ScopeGeometry, steps: int | None = None,
                from_straight: bool = True) -> np.ndarray:
    """Tip pose (base frame) of the free scope at ``q`` after settling: the check against ``fk``.

    The base is placed at ``[0, 0, q3]`` rolled by ``q2``; no actuation non-idealities.  With
    ``from_straight`` the segment starts straight and at rest and the joint springs bend it
    (``steps`` default: ``settle_time_s``); otherwise it starts at the targets.
    """
    sim = ScopeSim(params, geometry)
    try:
        q = np.asarray(q, float)
        base = np.eye(4)
        base[:3, :3] = _rz(q[1])
        base[:3, 3] = [0.0, 0.0, q[2]]
        sim.set_base(base)
        if not from_straight:
            sim.set_bend(q[0])
        sim.reset_joints()
        sim.set_bend(q[0])
        if steps is None:
            steps = int(round(max(params.settle_time_s, 0.05) / params.time_step_s))
        sim.step(steps)
        return sim.tip_pose()
    finally:
        sim.close()
