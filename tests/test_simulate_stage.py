"""The simulate stage's own geometry: opening the airway entrance for the scope."""
from __future__ import annotations

import numpy as np

from room_pipeline.io.mesh import Mesh
from room_pipeline.planning.trajectory import tum_text as tum
from room_pipeline.stages.simulate import open_entrance


def _tube(radius=5e-3, z0=0.0, z1=0.1, n=24, m=20):
    """A closed tube along z (side + two fan caps)."""
    th = 2 * np.pi * np.arange(n) / n
    rings = [np.stack([radius * np.cos(th), radius * np.sin(th), np.full(n, z)], 1) for z in np.linspace(z0, z1, m)]
    v = np.concatenate(rings + [np.array([[0, 0, z0], [0, 0, z1]])])
    f = []
    for k in range(m - 1):
        for i in range(n):
            a, b = k * n + i, k * n + (i + 1) % n
            f += [[a, b, b + n], [a, b + n, a + n]]
    c0, c1 = len(v) - 2, len(v) - 1
    for i in range(n):
        f += [[c0, (i + 1) % n, i], [c1, (m - 1) * n + i, (m - 1) * n + (i + 1) % n]]
    return Mesh(v, np.array(f))


def test_open_entrance_removes_only_the_proximal_cap_region():
    mesh = _tube()
    start = np.array([0.0, 0.0, 0.09])       # first pose 10 mm below the top cap
    tangent = np.array([0.0, 0.0, -1.0])     # looking down the tube
    opened, n = open_entrance(mesh, start, tangent, radius=5e-3)
    c = opened.vertices[opened.faces].mean(axis=1)
    assert n > 0 and opened.n_faces == mesh.n_faces - n
    assert np.all(c[:, 2] <= 0.09 + 1e-12)   # nothing left behind the start plane near the axis
    assert np.isclose(c[:, 2].min(), mesh.vertices[mesh.faces].mean(axis=1)[:, 2].min())  # far cap kept


def test_tum_text_has_unit_quaternions():
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, 3] = np.arange(9).reshape(3, 3) * 1e-3
    lines = [ln for ln in tum(np.array([0.0, 0.1, 0.2]), poses).splitlines() if not ln.startswith("#")]
    q = np.array([[float(x) for x in ln.split()[4:]] for ln in lines])
    assert len(lines) == 3 and np.allclose(np.linalg.norm(q, axis=1), 1.0)
