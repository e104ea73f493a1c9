"""The scope's collision surface (room_pipeline.anatomy.collision): decimation under a measured bound."""
from __future__ import annotations

import numpy as np
import pytest

from room_pipeline.anatomy.collision import collision_surface
from room_pipeline.anatomy.mesh import MeshParams
from room_pipeline.errors import ConfigError
from room_pipeline.geometry.open3d_adapter import surface_distance
from room_pipeline.io.mesh import Mesh


def tube(radius=5e-3, length=40e-3, n_around=64, n_along=80, wobble=0.0) -> Mesh:
    """An open cylinder (both ends open) along z, ~2 mm triangles, optionally bumpy."""
    a = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    z = np.linspace(0, length, n_along)
    A, Z = np.meshgrid(a, z)
    R = radius * (1 + wobble * np.sin(3 * A) * np.sin(40 * Z))
    V = np.stack([R * np.cos(A), R * np.sin(A), Z], -1).reshape(-1, 3)
    F = []
    for i in range(n_along - 1):
        for j in range(n_around):
            p, q = i * n_around + j, i * n_around + (j + 1) % n_around
            F += [[p, q, p + n_around], [q, q + n_around, p + n_around]]
    return Mesh(V, np.array(F, np.int64))


def two_sided_max_mm(a: Mesh, b: Mesh) -> float:
    return float(np.concatenate([surface_distance(a, b), surface_distance(b, a)]).max() * 1e3)


def test_bound_holds_and_faces_drop():
    m = tube(wobble=0.05)
    dec, rep = collision_surface(m, 0.5, 0.25)
    assert dec.n_faces < 0.6 * m.n_faces
    assert rep["error_max_mm"] <= 0.25
    assert two_sided_max_mm(dec, m) <= 0.25 + 1e-6      # independently re-measured
    assert rep["faces"] == dec.n_faces and rep["rounds"] >= 1


def test_open_rims_stay_in_place():
    m = tube()
    dec, _ = collision_surface(m, 0.25, 0.3)
    z = dec.vertices[:, 2]
    assert z.min() == pytest.approx(0.0, abs=1e-9) and z.max() == pytest.approx(40e-3, abs=1e-9)


def test_unreachable_bound_keeps_the_full_mesh():
    m = tube(wobble=0.2)
    dec, rep = collision_surface(m, 0.01, 1e-4, max_rounds=2)
    assert dec.n_faces == m.n_faces and "note" in rep and rep["fraction"] == 1.0
    np.testing.assert_array_equal(dec.vertices, m.vertices)


def test_fraction_one_and_tiny_meshes_are_copies():
    m = tube(n_around=8, n_along=4)                    # 48 faces: too small to decimate
    for frac in (1.0, 0.3):
        dec, rep = collision_surface(m, frac, 0.25)
        assert dec.n_faces == m.n_faces and rep["rounds"] == 0


def test_unreferenced_vertices_do_not_count_as_error():
    m = tube(wobble=0.05)
    far = Mesh(np.concatenate([m.vertices, [[1.0, 1.0, 1.0]]]), m.faces)   # a stray vertex 1 m away
    dec, rep = collision_surface(far, 0.5, 0.25)
    assert rep["error_max_mm"] <= 0.25 and dec.n_faces < far.n_faces


def test_deterministic():
    m = tube(wobble=0.05)
    a, _ = collision_surface(m, 0.5, 0.25)
    b, _ = collision_surface(m, 0.5, 0.25)
    assert a.vertices.tobytes() == b.vertices.tobytes() and a.faces.tobytes() == b.faces.tobytes()


@pytest.mark.parametrize("key,value", [("collision_decimation", 0.0), ("collision_decimation", 1.5),
                                       ("collision_max_error_mm", 0.0)])
def test_params_rejected(key, value):
    with pytest.raises(ConfigError, match=key):
        MeshParams(**{key: value})


def bumpy_tube() -> Mesh:
    """A fine open tube (5 mm radius) with three narrow 0.6 mm bumps: a quadric collapse to 2 % of the faces
    flattens them a little past 0.1 mm while the rest of the tube stays far inside."""
    m = tube(n_around=128, n_along=160)
    V = m.vertices.copy()
    a, z = np.arctan2(V[:, 1], V[:, 0]), V[:, 2]
    for a0, z0 in [(0.5, 0.01), (2.5, 0.02), (4.5, 0.03)]:
        da, dz = np.angle(np.exp(1j * (a - a0))) * 5e-3, z - z0
        bump = 0.6e-3 * np.exp(-(da ** 2 + dz ** 2) / (2 * 0.6e-3 ** 2))
        V[:, :2] *= (1 + bump / 5e-3)[:, None]
    return Mesh(V, m.faces)


def test_a_few_misses_keep_their_faces_the_rest_is_reduced():
    from room_pipeline.anatomy.decimate import QuadricOptions, _quadric

    m = bumpy_tube()
    plain = _quadric(m, int(0.02 * m.n_faces), QuadricOptions(), None)
    assert two_sided_max_mm(plain, m) > 0.1                 # the plain collapse misses the bound ...
    dec, rep = collision_surface(m, 0.02, 0.1)
    assert two_sided_max_mm(dec, m) <= 0.1 + 1e-6           # ... the routine meets it (re-measured)
    assert rep["protected_faces"] > 0 and rep["rounds"] >= 2
    assert dec.n_faces < 0.05 * m.n_faces                   # and still keeps < 5 % of the faces
    assert rep["error_input_to_output_max_mm"] <= 0.1 and rep["error_output_to_input_max_mm"] <= 0.1


def test_closed_input_gives_a_closed_collision_surface():
    from room_pipeline.anatomy.topology import mesh_topology
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.create_sphere(subdiv=5)                               # 20480 faces, radius 1 (mm after scaling)
    cm = ms.current_mesh()
    m = Mesh(cm.vertex_matrix() * 8e-3, cm.face_matrix())   # an 8 mm ball
    dec, rep = collision_surface(m, 0.1, 0.05)
    t = mesh_topology(dec)
    assert t["watertight"] and t["manifold"] and rep["error_max_mm"] <= 0.05 and dec.n_faces < m.n_faces


def test_no_import_cycle_between_mesh_and_collision():
    import ast
    from pathlib import Path

    import room_pipeline.anatomy as anatomy

    root = Path(anatomy.__file__).parent
    for name in ("collision.py", "decimate.py", "topology.py"):
        tree = ast.parse((root / name).read_text())
        mods = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert "mesh" not in mods, f"anatomy/{name} imports anatomy/mesh.py"


def test_open3d_is_imported_by_its_adapter_only():
    import re
    from pathlib import Path

    import room_pipeline

    src = Path(room_pipeline.__file__).parent
    hits = [str(p.relative_to(src)) for p in src.rglob("*.py")
            if re.search(r"^\s*(import open3d|from open3d)", p.read_text(), re.M)]
    assert hits == ["geometry/open3d_adapter.py"], hits


def test_misses_that_move_between_rounds_back_the_reduction_off(monkeypatch):
    """A quadric collapse is global: protecting one round's few misses can let a new miss appear elsewhere
    (AirQuant's render mesh missed 0.2 mm at 43, 2, 1, 2, 1 points in five rounds and was left undecimated).
    From round LOCAL_ONLY_ROUNDS on, a local round also reduces less everywhere, so a reduction the bound
    allows is found.  Simulated: a miss at a new place in every round until the kept fraction reaches 0.6."""
    from room_pipeline.anatomy import decimate as D

    m = tube(wobble=0.1)
    n = m.n_faces
    targets = []

    def fake_quadric(mesh, target, opts, protect):
        targets.append(target)
        return Mesh(mesh.vertices, mesh.faces[:target])    # the fake error below decides

    def fake_error(a, b, n_samples=0, seed=0, a_side=None):
        k = len(targets)
        kept = targets[-1] / n
        miss = 0.0 if kept >= 0.6 else 0.25
        pts = a.vertices[:1000]
        d = np.zeros(len(pts))
        d[(37 * k) % len(pts)] = miss * 1e-3                  # one point, somewhere new each round
        return {"a_pts": pts, "a_to_b": d, "b_pts": pts, "b_to_a": np.zeros(len(pts)), "max_mm": miss, "p95_mm": 0.0,
                "a_to_b_max_mm": miss, "b_to_a_max_mm": 0.0}

    monkeypatch.setattr(D, "_quadric", fake_quadric)
    monkeypatch.setattr(D, "two_sided_error", fake_error)
    _, r = D.decimate_under_bound(m, 0.25, 0.2, max_rounds=5, require_closed=False)
    assert "note" not in r and r["rounds"] <= 5
    kept = [t / n for t in targets]
    assert kept[1] == pytest.approx(kept[0], abs=0.05)            # round 2: local protection only
    assert kept[-1] >= 0.6 > kept[D.LOCAL_ONLY_ROUNDS - 1]        # then backed off until the bound held
