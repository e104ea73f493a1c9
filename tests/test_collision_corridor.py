"""The scope's wall at any mesh size: the corridor around the route and the split into Bullet bodies.

PyBullet's createCollisionShape fails above ~131k-200k faces (../shared/DESIGN.md); real lumen meshes
at 0.5-0.7 mm have 120k-500k.  The wall is the route's corridor, cut into bodies of <= max_body_faces.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from room_pipeline.errors import ConfigError
from room_pipeline.io.mesh import Mesh
from room_pipeline.robot.kinematics import DEFAULT_GEOMETRY as G
from room_pipeline.robot.pybullet_adapter import ScopeSim
from room_pipeline.robot.sim_params import SimParams
from room_pipeline.robot.simulation import simulate
from room_pipeline.robot.wall import route_corridor, split_faces

from .test_simulation import phantom, straight_trajectory, tube  # noqa: F401  (fixture)


def grid_floor(n: int, size: float = 0.2, z: float = 0.0) -> Mesh:
    """A flat square of n x n cells (2 n^2 triangles), normal +z, centred on the origin."""
    u = np.linspace(-size / 2, size / 2, n + 1)
    X, Y = np.meshgrid(u, u, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], axis=1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    b, c, d = a + (n + 1), a + 1, a + n + 2
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([c, b, d], 1)])
    return Mesh(V, F.astype(np.int64))


def test_split_faces_partitions_in_order():
    m = grid_floor(30)                                   # 1800 faces
    parts = split_faces(m.vertices, m.faces, 500)
    assert len(parts) == 4 and max(len(p) for p in parts) <= 500
    allf = np.concatenate(parts)
    assert np.array_equal(np.sort(allf), np.arange(m.n_faces))          # a partition
    assert all(np.all(np.diff(p) > 0) for p in parts)                    # each run sorted
    cen = m.vertices[m.faces].mean(axis=1)
    spans = [(cen[p, 0].min(), cen[p, 0].max()) for p in parts]          # compact slabs along x
    assert all(spans[i][1] <= spans[i + 1][0] + 1e-12 for i in range(3))
    assert len(split_faces(m.vertices, m.faces, 10_000)) == 1
    assert split_faces(m.vertices, m.faces[:0], 10) == []
    order = np.arange(m.n_faces)[::-1]
    assert np.array_equal(split_faces(m.vertices, m.faces, 900, order)[0], np.arange(900, 1800))


def test_wall_larger_than_pybullet_limit_loads_and_holds():
    """A 259,200-face wall (over the 200,914 faces PyBullet refused in one shape) loads as 3 bodies
    and a capsule dropped on it rests on it, touching it."""
    m = grid_floor(360)
    prm = SimParams()
    sim = ScopeSim(prm, G)
    try:
        sim.set_wall(m.vertices, m.faces)
        assert sim.wall_faces == 259_200 and len(sim.walls) == 3
        base = np.eye(4)
        base[:3, 3] = [0.0, 0.0, sim.radius + 0.2e-3]
        base[:3, :3] = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])   # scope lying along +y
        sim.set_base(base)
        sim.reset_joints()
        sim.step(50)
        force, pen = sim.contacts()
        pts = sim.sample_points()
    finally:
        sim.close()
    assert pen < 0.5e-3
    assert np.all(pts[:, 2] > sim.radius - 0.5e-3)


def test_split_wall_matches_one_body():
    """The same tube as one body or as 8 bodies: the same simulated poses within 0.05 mm."""
    tree, mesh = tube(length=0.2, radius=4e-3)
    tr = straight_trajectory([0.0, 0.0, -0.06], [0.0, 0.0, -1.0], 0.08, speed=0.02)
    one = simulate(tr, mesh, SimParams(collision_corridor_mm=0.0), G)
    many = simulate(tr, mesh, SimParams(collision_corridor_mm=0.0, max_body_faces=mesh.n_faces // 8 + 1), G)
    assert one.report["mesh"]["bodies"] == 1 and many.report["mesh"]["bodies"] == 8
    d = np.linalg.norm(one.tip_poses[:, :3, 3] - many.tip_poses[:, :3, 3], axis=1)
    assert d.max() < 0.05e-3


def test_route_corridor_keeps_faces_near_the_route_and_large_triangles_reaching_it():
    m = grid_floor(40, size=0.2)                       # cells of 5 mm
    samples = np.array([[x, 0.0, 0.0] for x in np.linspace(-0.05, 0.05, 101)])
    idx = route_corridor(m, samples, 0.01)
    V = m.vertices[m.faces]
    cen = V.mean(axis=1)
    near = np.flatnonzero((np.abs(cen[:, 1]) < 0.01) & (np.abs(cen[:, 0]) < 0.05))
    assert set(near) <= set(idx)                                       # everything the tube covers is kept
    reach = np.linalg.norm(V - cen[:, None], axis=2).max(axis=1)
    assert np.all(np.abs(cen[idx, 1]) - reach[idx] <= 0.01 + 1e-12)   # nothing that cannot reach it
    j = np.argmin(np.abs(cen[idx, 0][:, None] - samples[None, :, 0]), axis=1)
    assert np.all(np.diff(j) >= -1)                                    # ordered along the route
    big = Mesh(np.array([[-1.0, 0.02, 0], [1.0, 0.02, 0], [0.0, 1.0, 0]]), np.array([[0, 1, 2]]))
    assert list(route_corridor(big, samples, 0.01)) == [0]             # centroid 0.35 m away, edge 20 mm
    assert len(route_corridor(m, samples + [0, 0, 1.0], 0.01)) == 0    # route far away: nothing


def test_corridor_matches_whole_mesh_on_phantom(phantom):  # noqa: F811
    """Where the whole mesh fits, the corridor gives the same poses as the whole mesh (issue #17 item 4), to within
    what the order of the wall's triangles alone moves them: the whole mesh with its faces permuted moves the tip by
    up to 0.133 mm (frame 243; 95th percentile 0.011-0.016 mm over four orders), the corridor by 0.131 mm (p95 0.014):
    ``python benchmarks/collision_face_order.py``, benchmarks/results/collision_face_order.md.  A bound of 0.05 mm
    on the maximum held on earlier machines by chance of the contact order and failed on others."""
    tree, tr, mesh = phantom
    full = simulate(tr, mesh, SimParams(collision_corridor_mm=0.0), G)
    corr = simulate(tr, mesh, SimParams(), G)
    rep = corr.report["mesh"]
    assert rep["corridor_faces"] < mesh.n_faces and rep["corridor_margin_mm"] > 0
    assert corr.report["corridor_widened"] == []
    d = np.linalg.norm(full.tip_poses[:, :3, 3] - corr.tip_poses[:, :3, 3], axis=1)
    assert np.percentile(d, 95) < 0.05e-3, np.percentile(d, 95)
    assert d.max() < 0.2e-3, d.max()                    # face order alone: up to 0.133 mm (docstring)


def test_corridor_too_narrow_is_widened(phantom):  # noqa: F811
    tree, tr, mesh = phantom
    short = dataclasses.replace(tr, timestamps=tr.timestamps[:20], poses=tr.poses[:20], arclength=tr.arclength[:20])
    res = simulate(short, mesh, SimParams(collision_corridor_mm=1.0), G)   # narrower than the scope itself
    w = res.report["corridor_widened"]
    assert w and w[0]["corridor_mm"] == 1.0 and w[0]["corridor_margin_mm"] < 0
    assert res.report["mesh"].get("corridor_margin_mm", 1.0) >= 0


@pytest.mark.parametrize("key,value", [("max_body_faces", 0), ("max_body_faces", 1.5),
                                       ("collision_corridor_mm", -1.0), ("collision_corridor_mm", float("nan"))])
def test_params_rejected(key, value):
    with pytest.raises(ConfigError, match=key):
        SimParams(**{key: value})
