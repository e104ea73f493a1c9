"""Precomputed multi-bounce inter-reflection of the ray caster (render/indirect.py)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from room_pipeline.io.mesh import Mesh
from room_pipeline.render.camera import CameraIntrinsics, look_at
from room_pipeline.render.indirect import IndirectConfig, Radiosity, cosine_directions, vertex_normals_into_lumen
from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer
from room_pipeline.render.scene import Film, Scene, TipLight, TissueMaterial

o3d = pytest.importorskip("open3d")
MM = 1e-3


def sphere(radius=10 * MM, resolution=24) -> Mesh:
    """A closed sphere, outward faces (air inside -> tissue outside, the lumen convention)."""
    m = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    return Mesh(np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64))


def box(half=10 * MM) -> Mesh:
    """A closed cube subdivided into small triangles, outward faces."""
    m = o3d.geometry.TriangleMesh.create_box(2 * half, 2 * half, 2 * half).translate((-half, -half, -half))
    m = m.subdivide_midpoint(number_of_iterations=4)
    return Mesh(np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64))


def tube(radius=5 * MM, z0=-5 * MM, z1=60 * MM, n_theta=48, n_z=40) -> Mesh:
    """Open cylinder along +z, outward faces (as tests/test_raycast.py)."""
    th = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    zs = np.linspace(z0, z1, n_z)
    v = np.stack([np.broadcast_to(radius * np.cos(th), (n_z, n_theta)),
                  np.broadcast_to(radius * np.sin(th), (n_z, n_theta)), np.broadcast_to(zs[:, None], (n_z, n_theta))], -1)
    idx = np.arange(n_z * n_theta).reshape(n_z, n_theta)
    a, b = idx[:-1], np.roll(idx, -1, axis=1)[:-1]
    c, d = idx[1:], np.roll(idx, -1, axis=1)[1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return Mesh(v.reshape(-1, 3), faces)


def scene_of(mesh, pose, base=(0.5, 0.5, 0.5), light=None, res=48) -> Scene:
    cam = CameraIntrinsics.from_fov(res, res, 90.0)
    mat = TissueMaterial(base_color=base, specular=0.0)
    return Scene(mesh, cam, np.asarray([pose]), np.array([0.0]), material=mat,
                 light=light or TipLight(power_w=0.01, offset_m=(0.0, 0.0, 0.0)),
                 film=Film(exposure_ev=0.0, veiling_glare=0.0))


def radiosity(mesh, k=64, bounces=8, base=(0.5, 0.5, 0.5), seed=0):
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    return Radiosity(rc, mesh.vertices, mesh.faces, np.zeros(3), TissueMaterial(base_color=base, specular=0.0),
                     None, IndirectConfig(bounces=bounces, rays_per_point=k, seed=seed), nthreads=1)


def test_cosine_weighted_directions():
    n = vertex_normals_into_lumen(sphere().vertices, sphere().faces)[:50]
    d = cosine_directions(n, 64, 3)
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    cos = np.einsum("nkc,nc->nk", d, n)
    assert cos.min() >= 0
    assert abs(cos.mean() - 2 / 3) < 0.01            # E[cos] under a cosine-weighted hemisphere
    assert abs((cos ** 2).mean() - 0.5) < 0.01


@pytest.mark.parametrize("make", [sphere, box])
def test_white_furnace_closed_surface(make):
    """Every gather ray of a closed surface lands on it: rows of G sum to 1, and a uniform direct
    irradiance E0 with albedo rho gives E0 sum_{k<=n} rho^k after n bounces."""
    mesh = make()
    rad = radiosity(mesh, k=16, bounces=6)
    rows = np.asarray(rad.G.sum(axis=1)).ravel()
    assert np.allclose(rows, 1.0, atol=1e-5)
    e0 = np.full(mesh.n_vertices, 2.0, np.float32)
    ind = rad.indirect_irradiance(e0)
    expect = 2.0 * sum(0.5 ** k for k in range(1, 7))
    assert np.allclose(ind, expect, rtol=1e-4)
    # many bounces converge to the closed form E0 rho / (1 - rho)
    assert np.allclose(rad.indirect_irradiance(e0, bounces=60), 2.0 * 0.5 / 0.5, rtol=1e-4)


def test_indirect_zero_for_black_walls_and_zero_bounces():
    mesh = sphere()
    rad = radiosity(mesh, base=(0.0, 0.0, 0.0))
    e0 = np.ones(mesh.n_vertices, np.float32)
    assert not rad.indirect_irradiance(e0).any()
    rad = radiosity(mesh)
    assert not rad.indirect_irradiance(e0, bounces=0).any()


def test_gather_matrix_is_deterministic_and_seeded():
    a, b, c = radiosity(box(), seed=0), radiosity(box(), seed=0), radiosity(box(), seed=1)
    assert a.G.data.tobytes() == b.G.data.tobytes() and a.G.indices.tobytes() == b.G.indices.tobytes()
    assert c.G.nnz != a.G.nnz or c.G.data.tobytes() != a.G.data.tobytes()


def test_sphere_interior_matches_the_closed_form():
    """Point light at the centre of a sphere of radius R: E_dir = P/(4 pi R^2) everywhere, and with every
    bounce E = E_dir / (1 - rho); the pixel radiance is rho E / pi (specular 0)."""
    R, P, rho = 10 * MM, 0.01, 0.6
    mesh = sphere(R, resolution=30)
    pose = look_at(np.zeros(3), np.array([0.0, 0.0, 1.0]))
    sc = scene_of(mesh, pose, base=(rho,) * 3, light=TipLight(power_w=P, offset_m=(0.0, 0.0, 0.0)))
    rr = RaycastRenderer(sc, RaycastConfig(indirect=IndirectConfig(bounces=200, rays_per_point=16), nthreads=1))
    out = rr.render(0, ("rgb",))
    lin = out["rgb_linear"][out["hit"]]
    e_dir = P / (4 * math.pi * R * R)
    # the faceted sphere's vertices sit at R, its face centres slightly nearer: a fraction of a per cent
    np.testing.assert_allclose(lin.mean(axis=0), rho * e_dir / (1 - rho) / math.pi, rtol=0.01)
    ind = rr.radiosity.indirect_irradiance(rr.radiosity.direct_irradiance(pose, sc.light))
    np.testing.assert_allclose(ind.mean(), e_dir * rho / (1 - rho), rtol=0.01)


def test_render_with_indirect_is_finite_brighter_and_deterministic():
    mesh = tube()
    pose = look_at(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.05]))
    sc = scene_of(mesh, pose, light=TipLight(power_w=0.01, offset_m=(0.0, -1.1 * MM, 0.0), spot_exponent=2.767))
    base = RaycastRenderer(sc, RaycastConfig(nthreads=1)).render(0, ("rgb",))
    cfg = RaycastConfig(nthreads=1, indirect=IndirectConfig(bounces=8, rays_per_point=16))
    a = RaycastRenderer(sc, cfg).render(0, ("rgb",))
    b = RaycastRenderer(sc, cfg).render(0, ("rgb",))
    assert np.isfinite(a["rgb_linear"]).all()
    assert a["rgb"].tobytes() == b["rgb"].tobytes()
    diff = a["rgb_linear"] - base["rgb_linear"]
    assert diff.min() >= 0 and diff[a["hit"]].mean() > 0
    # the far, dim end of the tube gains relatively more than the lit wall near the tip
    y = a["rgb_linear"].sum(-1) / np.maximum(base["rgb_linear"].sum(-1), 1e-30)
    d = RaycastRenderer(sc, RaycastConfig(nthreads=1)).render(0, ("depth",))["depth"]
    hit = a["hit"]
    assert np.median(y[hit & (d > np.percentile(d[hit], 80))]) > np.median(y[hit & (d < np.percentile(d[hit], 20))])


def test_shadowed_points_get_no_direct_light():
    """Two rooms joined by nothing: a point behind a wall (seen from the light) gets no direct light with
    shadows on, and some with them off."""
    mesh = box()
    rc_mesh = mesh
    pose = look_at(np.array([0.0, 0.0, -5 * MM]), np.array([0.0, 0.0, 1.0]))
    sc = scene_of(rc_mesh, pose)
    import open3d as o3d

    # an inner blocker: a small closed cube in front of the light
    blk = o3d.geometry.TriangleMesh.create_box(4 * MM, 4 * MM, 1 * MM).translate((-2 * MM, -2 * MM, -3 * MM))
    v = np.concatenate([mesh.vertices, np.asarray(blk.vertices)])
    f = np.concatenate([mesh.faces, np.asarray(blk.triangles)[:, ::-1] + mesh.n_vertices])  # faces into the room
    m2 = Mesh(v, f)
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    on = Radiosity(rc, v, f, np.zeros(3), sc.material, None, IndirectConfig(bounces=1, rays_per_point=4), 1)
    off = Radiosity(rc, v, f, np.zeros(3), sc.material, None,
                    IndirectConfig(bounces=1, rays_per_point=4, shadows=False), 1)
    light = TipLight(power_w=0.01)
    e_on, e_off = on.direct_irradiance(pose, light), off.direct_irradiance(pose, light)
    # far wall (z = +10 mm) straight behind the blocker
    far = np.flatnonzero((np.abs(v[:, 2] - 10 * MM) < 1e-9) & (np.abs(v[:, 0]) < 1 * MM) & (np.abs(v[:, 1]) < 1 * MM))
    assert far.size and np.all(e_on[far] == 0) and np.all(e_off[far] > 0)
    assert m2.n_faces == len(f)


@pytest.mark.parametrize("bad", [{"indirect_bounces": -1}, {"indirect_rays_per_point": 0}])
def test_bad_indirect_config_is_refused(bad):
    from room_pipeline.errors import ConfigError
    from room_pipeline.render.params import RenderParams

    with pytest.raises(ConfigError, match="indirect"):
        RenderParams.from_dict(bad)


def test_render_config_reaches_the_ray_caster_and_the_meter():
    from room_pipeline.render.params import RenderParams, indirect_config, raycast_config

    p = RenderParams.from_dict({"indirect_bounces": 3, "indirect_rays_per_point": 9, "indirect_seed": 4})
    assert indirect_config(p) == IndirectConfig(bounces=3, rays_per_point=9, seed=4,
                                                max_edge_mm=RenderParams().indirect_max_edge_mm)
    assert indirect_config(RenderParams.from_dict({"indirect_max_edge_mm": 0.0})).max_edge_mm == 0.0
    assert raycast_config(p).indirect.bounces == 3
    assert not indirect_config(p).caustics
    assert indirect_config(RenderParams.from_dict({"indirect_caustics": True})).caustics


def test_walls_reached_by_bounced_light_pass_it_on_as_lambertian_walls_without_caustics():
    """Without caustics (the default, as Cycles renders with caustics_reflective off) the light a wall passes
    on is its albedo times what it receives, wet layer or not: the transport of a wet sphere is the dry
    sphere's.  With caustics the wet layer takes its share (white) and the old transport is kept.  The mirror
    ray of a pixel sees a wet wall either way (the same outgoing radiance in both modes)."""
    mesh = sphere()
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    pose = look_at(np.zeros(3), np.array([0.0, 0.0, 1.0]))
    light = TipLight(power_w=0.01, offset_m=(0.0, 0.0, 0.0))
    base = (0.6, 0.4, 0.3)
    out = {}
    for name, spec, caustics in (("dry", 0.0, False), ("wet", 0.5, False), ("wet_caustics", 0.5, True)):
        r = Radiosity(rc, mesh.vertices, mesh.faces, np.zeros(3), TissueMaterial(base_color=base, specular=spec),
                      None, IndirectConfig(bounces=4, rays_per_point=16, caustics=caustics), 1)
        out[name] = (r, r.frame(pose, light))
    np.testing.assert_allclose(out["wet"][1][1], out["dry"][1][1], rtol=1e-5)            # same indirect light
    np.testing.assert_allclose(out["wet"][0].rho_bounce, np.broadcast_to(base, (mesh.n_vertices, 3)), rtol=1e-6)
    wet_c = out["wet_caustics"][0]
    np.testing.assert_array_equal(wet_c.rho_bounce, wet_c.rho)
    # the wet layer's white share lifts the low-albedo channel most
    ratio = out["wet_caustics"][1][1].mean(axis=0) / out["wet"][1][1].mean(axis=0)
    assert ratio[2] > ratio[0]
    # what a mirror ray sees: the wet wall's direct light (1 bounce fewer), the same in both modes at 1 bounce
    one = [Radiosity(rc, mesh.vertices, mesh.faces, np.zeros(3), TissueMaterial(base_color=base, specular=0.5), None,
                     IndirectConfig(bounces=1, rays_per_point=16, caustics=c), 1).frame(pose, light)[2] for c in (0, 1)]
    np.testing.assert_allclose(one[0], one[1], rtol=1e-6)


def test_agrees_with_cycles_path_tracing_in_a_closed_sphere():
    """8 diffuse + glossy bounces inside a sphere lit from near its centre, on the same mesh and normals as
    Cycles (8 bounces, shadow rays, 64 spp, no sample clamp, no glossy filter).  Measured (64 spp): 0 bounces
    within 0.1 %, 1 bounce -0.6 to +1.0 %, 8 bounces +1.8 to +2.4 % (specular 0: within 0.1 % at 8 bounces, so
    the rest is the wet layer's share in the transport, treated as re-emitted evenly).  Before: 1 bounce
    +2.8 to +3.8 %, 8 bounces +5.8 to +6.4 %; the causes were the direct light re-emitted with the
    hemispherical albedo instead of at its incidence (Cycles scales the diffuse base on the outgoing side
    only, so its re-emitted share is albedo (1 - Abar) + A(n.l)), the mirror ray counting one bounce more than
    Cycles' max_bounces, and Cycles' default Filter Glossy 1.0 (~1 % darker)."""
    pytest.importorskip("bpy")
    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings

    mesh = sphere(10 * MM, resolution=30)
    pose = look_at(np.array([0.0, 0.0, -2 * MM]), np.array([0.0, 0.3, 1.0]))
    light = TipLight(power_w=0.01, offset_m=(0.0, -1.1 * MM, 0.0), radius_m=0.1 * MM)
    cam = CameraIntrinsics.from_fov(48, 48, 90.0)
    sc = Scene(mesh, cam, np.asarray([pose]), np.array([0.0]), light=light,
               material=TissueMaterial(base_color=(0.7, 0.4, 0.3)), film=Film(exposure_ev=0.0, veiling_glare=0.0))
    nb = 8
    rr = RaycastRenderer(sc, RaycastConfig(indirect=IndirectConfig(bounces=nb, rays_per_point=64), nthreads=1))
    ours = rr.render(0, ("rgb",))["rgb_linear"]
    st = CyclesSettings(samples=64, adaptive_threshold=0.0, denoise=False, exposure=0.0, max_bounces=nb,
                        cast_shadows=True, threads=1, clamp_indirect=0.0, filter_glossy=0.0)
    with CyclesRenderer(sc, st, vertex_normals=vertex_normals_into_lumen(mesh.vertices, mesh.faces)) as r:
        ref = r.render(0, ("rgb",))["rgb"]
    ratio = ours.reshape(-1, 3).mean(axis=0) / ref.reshape(-1, 3).mean(axis=0)
    assert np.all(np.abs(ratio - 1) < 0.035), ratio


def test_gather_matrix_is_built_once_per_mesh_in_a_process():
    from room_pipeline.render import indirect as ind

    mesh = box()
    a = radiosity(mesh, k=16, seed=11)
    b = radiosity(mesh, k=16, seed=11, base=(0.2, 0.3, 0.4))     # albedo is not part of G
    c = radiosity(mesh, k=16, seed=12)
    assert b.cached and b.G is a.G and not c.cached
    assert (c.G != a.G).nnz > 0
    ind._G_CACHE.clear()
    d = radiosity(mesh, k=16, seed=11)
    assert not d.cached and (d.G != a.G).nnz == 0                # rebuilt: the same bytes


def test_direct_light_is_re_emitted_at_its_incidence():
    """The wet layer reflects the tip light by A(n.l) (white) and the diffuse base keeps albedo (1 - Abar)
    (Cycles scales it on the outgoing side): near normal incidence less than the hemispherical rho; with
    specular 0 both are the albedo.  The mirror ray at a pixel sees the walls' light of one bounce fewer."""
    import open3d as o3d

    mesh = sphere()
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    cfg = IndirectConfig(bounces=1, rays_per_point=16)
    wet = Radiosity(rc, mesh.vertices, mesh.faces, np.zeros(3), TissueMaterial(base_color=(0.5, 0.5, 0.5), specular=0.5),
                    None, cfg, 1)
    cos = np.array([1.0, 0.5, 0.05], np.float32)
    rd = wet.direct_albedo(np.resize(cos, mesh.n_vertices))[:3]
    assert rd[0, 0] < wet.rho[0, 0] and rd[0, 0] < rd[2, 0]      # grazing light: the wet layer takes more
    np.testing.assert_allclose(rd[:, 0] - rd[:, 1], 0, atol=1e-7)  # white
    dry = Radiosity(rc, mesh.vertices, mesh.faces, np.zeros(3), TissueMaterial(base_color=(0.5, 0.5, 0.5), specular=0.0),
                    None, cfg, 1)
    np.testing.assert_allclose(dry.direct_albedo(np.resize(cos, mesh.n_vertices)), dry.rho, rtol=1e-6)
    pose = look_at(np.zeros(3), np.array([0.0, 0.0, 1.0]))
    ed, e_ind, lv = wet.frame(pose, TipLight(power_w=0.01, offset_m=(0.0, 0.0, 0.0)))
    _, cos_l = wet.direct(pose, TipLight(power_w=0.01, offset_m=(0.0, 0.0, 0.0)))
    # 1 bounce: the mirror ray sees the direct light re-emitted, not the bounced light
    np.testing.assert_allclose(lv, wet.direct_albedo(cos_l) * ed[:, None] / math.pi, rtol=1e-6)
    assert e_ind.mean() > 0


def radiosity_fine(mesh, max_edge_mm, k=16, bounces=6, base=(0.5, 0.5, 0.5)):
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    return Radiosity(rc, mesh.vertices, mesh.faces, np.zeros(3), TissueMaterial(base_color=base, specular=0.0),
                     None, IndirectConfig(bounces=bounces, rays_per_point=k, max_edge_mm=max_edge_mm), nthreads=1)


def test_refine_long_edges_keeps_the_surface_and_the_vertices():
    """Midpoint splits: no edge longer than the bound, the original vertices first and unchanged, the same
    area and orientation (summed vector area per original face region), closed stays closed (every edge in 2
    faces), the interpolation matrix reproduces the new vertices, deterministic; a bad length is refused."""
    from room_pipeline.render.refine import refine_long_edges

    mesh = tube(radius=5 * MM, z0=-30 * MM, z1=30 * MM, n_theta=10, n_z=21)
    for m in (mesh, sphere(resolution=8)):
        v, f, interp = refine_long_edges(m.vertices, m.faces, 1.0 * MM)
        assert np.array_equal(v[:m.n_vertices], m.vertices) and len(v) > m.n_vertices
        e = np.sort(np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
        assert np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).max() <= 1.0 * MM + 1e-12
        area = lambda vv, ff: np.cross(vv[ff[:, 1]] - vv[ff[:, 0]], vv[ff[:, 2]] - vv[ff[:, 0]])   # noqa: E731
        np.testing.assert_allclose(np.linalg.norm(area(v, f), axis=1).sum(),
                                   np.linalg.norm(area(m.vertices, m.faces), axis=1).sum(), rtol=1e-9)
        np.testing.assert_allclose(np.asarray(interp @ m.vertices), v, atol=1e-15)
        v2, f2, _ = refine_long_edges(m.vertices, m.faces, 1.0 * MM)
        assert v2.tobytes() == v.tobytes() and f2.tobytes() == f.tobytes()
    _, counts = np.unique(np.sort(np.stack([f, np.roll(f, -1, axis=1)], 2).reshape(-1, 2), 1), axis=0,
                          return_counts=True)
    assert set(counts) == {2}                                   # the closed sphere stays closed
    # orientation kept: the refined sphere's normals still point out (vertex_normals_into_lumen inward)
    nrm = vertex_normals_into_lumen(v, f)
    assert (np.einsum("ij,ij->i", nrm, v) < 0).all()
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError):
            refine_long_edges(mesh.vertices, mesh.faces, bad)


@pytest.mark.parametrize("make", [sphere, box])
def test_transport_mesh_keeps_the_white_furnace_and_the_render_vertices(make):
    """The transport on the refined mesh: rows of G sum to 1 on a closed surface, a uniform irradiance
    gives the closed form, the render mesh's vertices are its first points; deterministic."""
    mesh = make()
    rad = radiosity_fine(mesh, 0.8)
    assert rad.n_render == mesh.n_vertices and len(rad.vertices) > mesh.n_vertices
    assert np.array_equal(rad.vertices[:mesh.n_vertices], mesh.vertices)
    assert np.allclose(np.asarray(rad.G.sum(axis=1)).ravel(), 1.0, atol=1e-5)
    e0 = np.full(len(rad.vertices), 2.0, np.float32)
    assert np.allclose(rad.indirect_irradiance(e0), 2.0 * sum(0.5 ** k for k in range(1, 7)), rtol=1e-4)
    again = radiosity_fine(mesh, 0.8)
    assert again.G.data.tobytes() == rad.G.data.tobytes() and again.G.indices.tobytes() == rad.G.indices.tobytes()


def exact_direct_power(rad, pose, light, m=64):
    """The tip light's power on the surface (W): a fine quadrature of its irradiance, m^2 sub-triangle
    centroids on every face (interpolated normals, shadow rays: Radiosity.point_irradiance)."""
    q = [((i + 1 / 3) / m, (j + 1 / 3) / m) for i in range(m) for j in range(m - i)] + \
        [((i + 2 / 3) / m, (j + 2 / 3) / m) for i in range(m - 1) for j in range(m - 1 - i)]
    b = np.array([(1 - a - c, a, c) for a, c in q])                       # (m^2, 3), equal weights
    pose = np.asarray(pose, dtype=np.float64)
    lp = pose[:3, :3] @ np.asarray(light.offset_m, dtype=np.float64) + pose[:3, 3]
    total = 0.0
    for f in np.array_split(np.arange(len(rad.faces)), 8):
        tri = rad.faces[f]
        p = np.einsum("qc,fcd->fqd", b, rad.vertices[tri]).reshape(-1, 3)
        n = np.einsum("qc,fcd->fqd", b, rad.normals[tri])
        n = (n / np.linalg.norm(n, axis=2, keepdims=True)).reshape(-1, 3)
        e = rad.point_irradiance(p, n, lp, pose[:3, 2], light).reshape(len(f), len(b))
        total += float((rad.face_area[f] * e.mean(axis=1)).sum())
    return total


def test_transport_mesh_carries_the_tip_light_power_on_a_coarse_tube():
    """A light 1.5 mm from the wall of a coarse tube (edges ~3 mm): the vertex samples' linear interpolant
    misses > 2 % of the power the wall receives (a fine quadrature of the exact irradiance); on the refined
    transport mesh it carries it within 1.5 %."""
    mesh = tube(radius=5 * MM, z0=-30 * MM, z1=30 * MM, n_theta=10, n_z=21)
    light = TipLight(power_w=0.01, offset_m=(0.0, 0.0, 0.0))
    pose = look_at(np.array([0.0, 3.5 * MM, 0.0]), np.array([0.0, 0.0, 1.0]))
    coarse = radiosity_fine(mesh, 0.0, k=4, bounces=1)
    ev, _ = coarse.direct(pose, light)
    exact = exact_direct_power(coarse, pose, light)
    rad = radiosity_fine(mesh, 0.5, k=4, bounces=1)
    ef, _ = rad.direct(pose, light)
    p_fine = float((ef.astype(np.float64) * rad.vertex_mass).sum())
    p_coarse = float((ev.astype(np.float64) * coarse.vertex_mass).sum())
    assert abs(p_fine / exact - 1) < 0.015 and abs(p_coarse / exact - 1) > 0.02
    # the frame's arrays cover the transport points; the render vertices come first
    ed, e_ind, lv = rad.frame(pose, light)
    assert len(ed) == len(e_ind) == len(lv) == len(rad.vertices) and np.isfinite(e_ind).all()


def test_max_edge_is_checked_and_reaches_the_ray_caster():
    from room_pipeline.errors import ConfigError
    from room_pipeline.render.params import RenderParams, indirect_config

    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="max_edge_mm"):
            IndirectConfig(max_edge_mm=bad)
    with pytest.raises(ConfigError):
        RenderParams.from_dict({"indirect_max_edge_mm": -0.5})
    assert indirect_config(RenderParams.from_dict({"indirect_max_edge_mm": 1.5})).max_edge_mm == 1.5
    assert IndirectConfig().max_edge_mm == 0.0


def test_render_with_a_transport_mesh_is_finite_and_deterministic():
    mesh = tube()
    pose = look_at(np.array([0.0, 2 * MM, 0.0]), np.array([0.0, 0.0, 1.0]))
    cfg = RaycastConfig(indirect=IndirectConfig(bounces=3, rays_per_point=4, max_edge_mm=1.0), nthreads=1)
    a = RaycastRenderer(scene_of(mesh, pose), cfg).render(0, ("rgb",))
    b = RaycastRenderer(scene_of(mesh, pose), cfg).render(0, ("rgb",))
    assert np.isfinite(a["rgb_linear"]).all() and a["rgb"].tobytes() == b["rgb"].tobytes()
    off = RaycastRenderer(scene_of(mesh, pose), dataclasses.replace(
        cfg, indirect=dataclasses.replace(cfg.indirect, max_edge_mm=0.0))).render(0, ("rgb",))
    assert a["rgb_linear"][a["hit"]].mean() > 0 and off["rgb_linear"].tobytes() != a["rgb_linear"].tobytes()


@pytest.mark.parametrize("caustics", [False, True])
def test_uniform_albedo_power_series_matches_the_general_bounce_loop(caustics):
    """An untextured scene (the exposure meter's) takes the single-column power series of ``_bounce``; it gives
    the values of the general three-column Jacobi loop (forced by marking the albedo non-uniform), for the
    tip light's frame and for a uniform source, with and without caustics."""
    import open3d as o3d

    mesh = box()
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    cfg = IndirectConfig(bounces=5, rays_per_point=16, caustics=caustics)
    mat = TissueMaterial(base_color=(0.8, 0.45, 0.3), specular=0.5)
    fast = Radiosity(rc, mesh.vertices, mesh.faces, np.zeros(3), mat, None, cfg, 1)
    assert fast.uniform_albedo
    slow = Radiosity(rc, mesh.vertices, mesh.faces, np.zeros(3), mat, None, cfg, 1)
    slow.uniform_albedo = False
    pose = look_at(np.zeros(3), np.array([0.3, 0.2, 1.0]))
    light = TipLight(power_w=0.01, offset_m=(0.0, 0.0, 0.0))
    for a, b in zip(fast.frame(pose, light), slow.frame(pose, light)):
        np.testing.assert_allclose(a, b, rtol=2e-5, atol=1e-7 * float(np.abs(b).max()))
    e0 = np.linspace(0.0, 3.0, mesh.n_vertices).astype(np.float32)
    np.testing.assert_allclose(fast.indirect_irradiance(e0), slow.indirect_irradiance(e0), rtol=2e-5)
    textured = Radiosity(rc, mesh.vertices, mesh.faces, np.zeros(3), mat,
                         np.linspace(0.2, 0.8, 3 * mesh.n_vertices).reshape(-1, 3), cfg, 1)
    assert not textured.uniform_albedo


def test_columns_product_is_the_multi_vector_product_bit_for_bit():
    """The bounces multiply one column at a time; SciPy's single-vector CSR product sums each row in the same
    order as its multi-vector one, so the result is the same bytes (what keeps the default run's frames)."""
    import scipy.sparse as sp

    from room_pipeline.render.indirect import _columns_product

    rng = np.random.default_rng(3)
    g = sp.random(500, 500, density=0.05, random_state=4, format="csr", dtype=np.float32)
    x = rng.random((500, 3)).astype(np.float32)
    assert _columns_product(g, x).tobytes() == np.asarray(g @ x, dtype=np.float32).tobytes()
