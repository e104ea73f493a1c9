"""Fast renderer: Open3D ray casting of the lumen mesh, every modality from one cast per frame.

Open3D itself is imported only by :mod:`room_pipeline.geometry.open3d_adapter`; this module builds on it.

Over 500 lines because :class:`RaycastRenderer` is one job, every modality from one cast per frame: depth,
normals, flow, segmentation and the RGB shading all read the same per-frame hit arrays (triangle ids,
barycentrics, ray directions) held by the class, so splitting it would pass those arrays between modules for
no reuse; the light transport itself is apart (shading.py, indirect.py, texture.py).  Usage::

    r = RaycastRenderer(scene)                       # builds the BVH once
    out = r.render(i, {"rgb", "depth", "flow"})      # only these are computed
    out["depth"], out["hit"], out["flow"], out["flow_valid"], out["rgb"]

Ray casting
    The mesh goes into an ``o3d.t.geometry.RaycastingScene`` once (vertices
    float32, shifted by the mesh's bounding-box centre to keep float32
    precision; everything is shifted back).  Each pixel's ray is
    ``CameraIntrinsics.pixel_rays`` (camera-frame direction with z = 1, so the
    hit parameter *is* planar depth), rotated by the pose and started on the
    **near plane** (origin ``c + near * d``): geometry closer than ``near`` is
    clipped as in Cycles (whose clipping is planar too); hits beyond ``far``
    are no-hit.  One cast per frame, cached (``cache_frames``) so that the
    flow of frame t reuses the cast of t+1 when the sequence is rendered in
    order.

Outputs of :meth:`RaycastRenderer.render` (always ``hit``: (H, W) bool)
    ``depth``          (H, W) float32 planar z (metres); 0 where no hit.
    ``relative_depth`` (H, W) uint16 normalised inverse depth of the frame:
                       ``1 + round(65534 (1/d - 1/d_max) / (1/d_min - 1/d_max))``
                       on hit pixels (d_min/d_max: the frame's nearest/farthest
                       hit; 65535 = nearest, 1 = farthest), 0 = no hit;
                       ``relative_depth_range`` = [d_min, d_max] (float64,
                       metres) for the metadata.  Decode:
                       ``1/d = 1/d_max + (r - 1) / 65534 (1/d_min - 1/d_max)``.
    ``normals``        (H, W, 3) float32 unit normals in the **camera** frame,
                       facing the camera (``n . ray < 0``); 0 where no hit.
                       ``RaycastConfig.smooth_normals`` (default): vertex
                       normals (area-weighted) interpolated barycentrically
                       (Blender's 'shade smooth'); otherwise face normals.
    ``segmentation``   (H, W) int32: ``Scene.face_labels`` of the hit triangle
                       (0 for every surface pixel without labels), -1 = no hit;
                       also ``primitive_ids`` (H, W) int32 triangle index, -1 = no hit.
    ``world_points``   (H, W, 3) float64 hit points, world RAS+ metres (0 where no hit).
    ``point_cloud``    (N, 3) float32 hit points in the **camera** frame (metres),
                       row-major over hit pixels; ``point_cloud_normals``
                       (N, 3) float32 (camera frame), ``point_cloud_pixels``
                       (N, 2) int32 (u, v), ``point_cloud_colors`` (N, 3)
                       uint8 when ``rgb`` is rendered too.  z equals ``depth``
                       at the pixel, so the cloud re-projects onto the depth
                       map (:func:`write_point_cloud` writes the PLY).
    ``rgb``            (H, W, 3) uint8 (:mod:`room_pipeline.render.shading`; a
                       textured material's appearance function is evaluated at
                       every hit, :meth:`RaycastRenderer.albedo_per_pixel`, or its
                       vertex bake interpolated, :meth:`RaycastRenderer.albedo`;
                       the frame's exposure (``Film.frame_ev`` when set),
                       vignetting, veiling glare and response curve applied);
                       ``rgb_linear`` (H, W, 3) float32 linear radiance x 2^EV x
                       vignetting (before glare and clipping); black where no hit.
    ``flow``           (H, W, 2) float32 forward flow t -> t+1 and ``flow_valid``
                       (H, W) bool (:mod:`room_pipeline.render.flow`); the last
                       frame has no successor: flow 0, nothing valid.
"""
from __future__ import annotations

import collections
import dataclasses
import os
import time
from typing import Iterable

import numpy as np

from ..conventions import metadata_block
from ..io.ply import write_ply
from . import flow as flowmod
from .indirect import IndirectConfig, Radiosity
from .scene import Scene
from .shading import (VIEW_TRANSFORMS, apply_response, auto_exposure_ev, interreflection, shade_coaxial,
                      shade_linear, specular_albedo_at)

MODALITIES = frozenset({"rgb", "depth", "relative_depth", "normals", "flow", "point_cloud", "segmentation",
                        "world_points"})
OCCLUSION_MODES = ("depth", "raycast")
_INVALID = np.uint32(0xFFFFFFFF)


@dataclasses.dataclass(frozen=True)
class RaycastConfig:
    """Knobs of the fast renderer.

    smooth_normals: interpolated vertex normals (True) or face normals.
    flow_occlusion: 'depth' -- test visibility at t+1 against frame t+1's
        depth map (inverse-depth bilinear, no extra cast; conservative at
        depth edges) -- or 'raycast' -- cast a ray through ``p'`` (exact, one
        more cast per frame).
    occlusion_abs_tol_m / occlusion_rel_tol: visible when the surface at t+1
        is within ``abs + rel * z`` of the point's depth ``z``.
    nthreads: Open3D ray-casting threads (0 = all cores).
    cache_frames: how many frames' casts are kept.
    per_pixel_texture: evaluate the mucosa appearance function at every hit
        (True, what Cycles evaluates per shading point) or interpolate its per-vertex bake (False).
    shading_stride: the appearance's smooth noise fields are evaluated every
        ``shading_stride`` pixels and bilinearly interpolated (the sharp
        vessel threshold, rings and folds stay per pixel); 1 = every pixel
        (benchmarks/realism_speed.py: error vs speed).
    indirect: multi-bounce diffuse inter-reflection precomputed on the mesh
        (:mod:`room_pipeline.render.indirect`; ``bounces`` 0 = off).
    transport_albedo: the vertex albedo of the inter-reflection with the per-pixel
        appearance: 'area_mean' (the appearance function averaged over each
        vertex's hat function, :func:`~room_pipeline.render.texture.vertex_albedo_area_mean`:
        walls re-emit with their mean albedo) or 'point' (its value at the vertex,
        :meth:`Scene.vertex_albedo`, which aliases detail finer than the vertex
        spacing; against Cycles' per-shading-point reference, 600x600 tile grid:
        trachea 38.2 -> 38.9 dB, bifurcation 37.6 -> 38.9 dB, distal 41.3 -> 41.4 dB,
        benchmarks/results/realism_indirect_grid.md).  Without ``per_pixel_texture`` the
        transport uses the point bake, as the pixels do.
    direct_shadows: a shadow ray from every hit to the tip light for the per-pixel direct term (True), or
        none (False, default: the light sits next to the lens, so what the camera sees is lit, as
        :mod:`~room_pipeline.render.shading` assumes).  With the LED off the optical centre
        (``TipLight.offset_m``) a fold within a few mm of the tip can hide from the light walls the lens
        still sees (``tests/test_realism.py::test_a_frame_in_the_shadow_of_a_fold``); off, those walls are
        lit as if nothing were between.  One more cast per frame; not the default (the default RGB's figures
        were measured without it).  The inter-reflection's vertex direct light always has shadow rays.
    edge_samples: the pixel filter at silhouettes (:mod:`room_pipeline.render.antialias`): pixels at a depth
        discontinuity (a relative jump of ~``edge_depth_jump`` in 1/depth; or hit next to no hit) are shaded
        at ``edge_samples`` x ``edge_samples`` sub-pixel offsets at the quantiles of Cycles' pixel filter
        (Blackman-Harris, 1.5 px) and averaged; 0 = one ray through every pixel centre.  RGB only: depth,
        normals, flow and segmentation stay the centre ray's (exact per-pixel geometry).
    """

    smooth_normals: bool = True
    flow_occlusion: str = "depth"
    occlusion_abs_tol_m: float = 2e-5
    occlusion_rel_tol: float = 1e-2
    nthreads: int = 0
    cache_frames: int = 2
    per_pixel_texture: bool = True
    shading_stride: int = 2
    indirect: IndirectConfig = IndirectConfig()
    transport_albedo: str = "area_mean"
    direct_shadows: bool = False
    edge_samples: int = 0
    edge_depth_jump: float = 0.15

    def __post_init__(self) -> None:
        if self.edge_samples < 0 or not self.edge_depth_jump > 0:
            raise ValueError(f"edge_samples must be >= 0 and edge_depth_jump > 0, got {self.edge_samples}, "
                             f"{self.edge_depth_jump}")
        if self.transport_albedo not in ("area_mean", "point"):
            raise ValueError(f"transport_albedo must be 'area_mean' or 'point', got {self.transport_albedo!r}")
        if self.flow_occlusion not in OCCLUSION_MODES:
            raise ValueError(f"flow_occlusion must be one of {OCCLUSION_MODES}, got {self.flow_occlusion!r}")
        if self.shading_stride < 1:
            raise ValueError("shading_stride must be >= 1")
        if self.cache_frames < 2:
            raise ValueError("cache_frames must be >= 2 (flow needs frames t and t+1)")


@dataclasses.dataclass
class Cast:
    """One frame's ray cast (views on Open3D's buffers, (H, W) layout).

    depth float32 (0 = no hit), hit bool, prim uint32 (0xFFFFFFFF = no hit),
    uv float32 (H, W, 2) barycentrics (hit = (1-u-v) v0 + u v1 + v v2).
    """

    depth: np.ndarray
    hit: np.ndarray
    prim: np.ndarray
    uv: np.ndarray


class RaycastRenderer:
    """Open3D ray-casting backend for a :class:`~room_pipeline.render.scene.Scene`."""

    def __init__(self, scene: Scene, config: RaycastConfig | None = None) -> None:
        from ..geometry.open3d_adapter import o3d as open3d_module

        o3d = open3d_module()
        self._o3d = o3d
        self.scene = scene
        self.config = config or RaycastConfig()
        if scene.film.view_transform not in VIEW_TRANSFORMS:
            raise ValueError(f"film.view_transform must be one of {VIEW_TRANSFORMS}")
        mesh = scene.mesh
        if scene.face_labels is not None and len(scene.face_labels) != mesh.n_faces:
            raise ValueError(f"face_labels has {len(scene.face_labels)} entries for {mesh.n_faces} faces")
        v = mesh.vertices
        self.origin = 0.5 * (v.min(axis=0) + v.max(axis=0)) if len(v) else np.zeros(3)
        self._rc = o3d.t.geometry.RaycastingScene()
        self._rc.add_triangles(o3d.core.Tensor((v - self.origin).astype(np.float32)),
                               o3d.core.Tensor(mesh.faces.astype(np.uint32)))
        cam = scene.camera
        self.rays = cam.pixel_rays()                                  # (H, W, 3) float64, z = 1
        self._rays32 = self.rays.reshape(-1, 3).astype(np.float32)
        self._rays_soa = tuple(np.ascontiguousarray(self._rays32[:, k]) for k in range(3))   # x, y, z
        self._unit_z = bool(np.all(self._rays_soa[2] == 1.0))
        len2 = np.einsum("hwi,hwi->hw", self.rays, self.rays)
        self._ray_len2 = len2.astype(np.float32)
        self._inv_ray_len = (1.0 / np.sqrt(len2)).astype(np.float32)
        va = scene.vertex_albedo()
        if va is not None and len(va) != mesh.n_vertices:
            raise ValueError(f"vertex_albedo has {len(va)} rows for {mesh.n_vertices} vertices")
        self._albedo_tab: np.ndarray | None = None
        if va is not None:                      # per-face corner albedo, components first; column F = no hit
            tab = np.zeros((9, mesh.n_faces + 1), dtype=np.float32)
            tab[:, :-1] = np.asarray(va, dtype=np.float32)[mesh.faces].reshape(-1, 9).T
            self._albedo_tab = tab
        tex = scene.material.texture
        self._per_pixel = bool(self.config.per_pixel_texture and tex is not None and tex.enabled)
        self._airway_tab: np.ndarray | None = None
        if self._per_pixel and scene.vertex_airway is not None:
            at = np.zeros((12, mesh.n_faces + 1), dtype=np.float32)
            at[:, :-1] = np.asarray(scene.vertex_airway, dtype=np.float32)[mesh.faces].reshape(-1, 12).T
            self._airway_tab = at
        self._face_normals: np.ndarray | None = None
        self._corner_normals: np.ndarray | None = None
        vv, uu = np.mgrid[0:cam.height, 0:cam.width]
        self._pixels = np.stack([uu, vv], axis=-1).astype(np.int32)
        self._labels = (None if scene.face_labels is None
                        else np.append(np.asarray(scene.face_labels, dtype=np.int32), np.int32(-1)))
        self._cache: collections.OrderedDict[int, Cast] = collections.OrderedDict()
        self._exposure_ev: float | None = scene.film.exposure_ev
        self._radiosity: Radiosity | None = None
        self._rad_frame: tuple | None = None          # (frame index, Radiosity.frame of it): the last frame's
        self.timings: dict[str, float] = collections.defaultdict(float)   # seconds, accumulated per step
        self.cast_count = 0

    # ------------------------------------------------------------------ casting
    def __len__(self) -> int:
        return len(self.scene.poses)

    def _ray_matrix(self, pose: np.ndarray) -> np.ndarray:
        """(4, 6) ``M`` with ``[d, 1] @ M = [origin, direction]``, the world ray of camera-frame direction ``d``.

        direction = R d, origin = c + near R d (on the near plane; c in the scene's shifted frame).
        """
        pose = np.asarray(pose, dtype=np.float64)
        R = pose[:3, :3]
        m = np.zeros((4, 6))
        m[:3, :3] = self.scene.camera.near * R.T
        m[3, :3] = pose[:3, 3] - self.origin
        m[:3, 3:] = R.T
        return m

    def _cast_rays(self, pose: np.ndarray, dirs_cam: np.ndarray) -> dict:
        """Cast camera-frame directions (N, 3) float32 (z = 1) from the pose's near plane.

        Each of the six float32 columns of the (N, 6) rays is ``x M[0] + y M[1] + z M[2] + M[3]``
        (:meth:`_ray_matrix`), from the direction components stored contiguously (built once for the
        image's ``pixel_rays()``): a few vector operations a frame, no (N, 3) rotation through strided
        views, and no BLAS call (whose thread pool spins on a loaded machine).
        """
        if dirs_cam is self._rays32:
            x, y, z = self._rays_soa
        else:
            d = np.asarray(dirs_cam, dtype=np.float32)
            x, y, z = (np.ascontiguousarray(d[:, k]) for k in range(3))
        m = self._ray_matrix(pose).astype(np.float32)
        n = len(x)
        rays = np.empty((n, 6), dtype=np.float32)
        acc, tmp = np.empty(n, dtype=np.float32), np.empty(n, dtype=np.float32)
        unit_z = z is self._rays_soa[2] and self._unit_z
        for k in range(6):
            np.multiply(x, m[0, k], out=acc)
            np.multiply(y, m[1, k], out=tmp)
            acc += tmp
            if unit_z:
                acc += m[2, k] + m[3, k]
            else:
                np.multiply(z, m[2, k], out=tmp)
                acc += tmp
                acc += m[3, k]
            rays[:, k] = acc
        out = self._rc.cast_rays(self._o3d.core.Tensor.from_numpy(rays), nthreads=self.config.nthreads)
        self.cast_count += 1
        return out

    def _depth_from(self, out: dict) -> tuple[np.ndarray, np.ndarray]:
        cam = self.scene.camera
        t = out["t_hit"].numpy()
        depth = t + np.float32(cam.near)                  # inf stays inf
        hit = depth <= np.float32(cam.far)                # False for inf (no hit) and beyond the far plane
        depth[~hit] = 0.0
        return depth, hit

    def cast(self, frame_index: int) -> Cast:
        """The (cached) cast of one frame."""
        i = self._index(frame_index)
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        t0 = time.perf_counter()
        cam = self.scene.camera
        h, w = cam.height, cam.width
        out = self._cast_rays(self.scene.poses[i], self._rays32)
        depth, hit = self._depth_from(out)
        prim = out["primitive_ids"].numpy()
        prim[~hit] = _INVALID
        c = Cast(depth=depth.reshape(h, w), hit=hit.reshape(h, w), prim=prim.reshape(h, w),
                 uv=out["primitive_uvs"].numpy().reshape(h, w, 2))
        self.timings["cast"] += time.perf_counter() - t0
        self._cache[i] = c
        while len(self._cache) > self.config.cache_frames:
            self._cache.popitem(last=False)
        return c

    def depth_at(self, pose: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact planar depth (float32, 0 = no hit) and hit mask at sub-pixel positions ``uv`` (N, 2) of a camera at ``pose``."""
        cam = self.scene.camera
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        d = cam.rays_at(uv)                    # undistorted direction of each (distorted) image position
        if len(d) == 0:
            return np.zeros(0, np.float32), np.zeros(0, bool)
        out = self._cast_rays(np.asarray(pose, dtype=np.float64), d.astype(np.float32))
        return self._depth_from(out)

    def _index(self, frame_index: int) -> int:
        n = len(self.scene.poses)
        i = int(frame_index)
        if not 0 <= i < n:
            raise IndexError(f"frame {frame_index} out of range (0..{n - 1})")
        return i

    # ------------------------------------------------------------------ geometry
    def _face_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World-frame unit face normals (F, 3), first vertices (F, 3) and per-face corner vertex normals (F, 9)."""
        if self._corner_normals is None:
            m = self.scene.mesh
            v, f = m.vertices, m.faces
            fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])      # length = 2 area
            vn = np.zeros_like(v)
            for k in range(3):
                np.add.at(vn, f[:, k], fn)                                     # area-weighted
            ln = np.linalg.norm(vn, axis=1, keepdims=True)
            vn = vn / np.where(ln > 0, ln, 1.0)
            lf = np.linalg.norm(fn, axis=1, keepdims=True)
            self._face_normals = fn / np.where(lf > 0, lf, 1.0)
            self._corner_normals = vn[f].reshape(-1, 9)
        return self._face_normals, self.scene.mesh.vertices[self.scene.mesh.faces[:, 0]], self._corner_normals

    def camera_normals(self, i: int, c: Cast) -> tuple[np.ndarray, np.ndarray]:
        """Unit normals in the camera frame facing the camera, (H, W, 3) float32 (0 where no hit), and ``n . ray`` (H, W).

        The side is per triangle: the face normal is flipped when the camera
        centre lies on its back (``n_f . (v0 - c) > 0``), which is the sign of
        ``n_f . ray`` for every ray hitting the face.  Smooth normals are the
        corner normals of that side, interpolated; where one would not face
        the camera (silhouettes) the face normal is used.
        """
        pose = self.scene.poses[i]
        R, centre = pose[:3, :3], pose[:3, 3]
        fn, v0, corners = self._face_tables()
        nf = len(fn)
        flip = np.where(np.einsum("ij,ij->i", fn, v0 - centre) > 0, -1.0, 1.0)
        prim = np.where(c.hit, c.prim, np.uint32(nf)).astype(np.intp).reshape(-1)
        rx, ry = self._rays_soa[:2]
        # per-frame tables, camera frame, side folded in, components first (structure of arrays)
        flat = np.zeros((3, nf + 1), dtype=np.float32)
        flat[:, :-1] = ((fn * flip[:, None]) @ R).T                            # R^T n
        if self.config.smooth_normals:
            tab = np.zeros((9, nf + 1), dtype=np.float32)
            tab[:, :-1] = ((corners.reshape(-1, 3) @ R).reshape(-1, 9) * flip[:, None]).T
            uv = c.uv.reshape(-1, 2)
            a, b = uv[:, 0], uv[:, 1]
            w0 = 1 - a - b
            n = np.empty((3, len(prim)), dtype=np.float32)
            for j in range(3):
                n[j] = tab[j].take(prim) * w0
                n[j] += tab[3 + j].take(prim) * a
                n[j] += tab[6 + j].take(prim) * b
            ln = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
            nr = n[0] * rx + n[1] * ry + n[2]
            bad = (nr >= -1e-7 * ln) | (ln <= 1e-12)          # back-facing interpolated normal, or no hit
            ln[bad] = 1.0
            inv = np.float32(1) / ln
            n *= inv
            nr *= inv
            if bad.any():
                idx = np.flatnonzero(bad)
                pi = prim[idx]
                n[:, idx] = flat[:, pi]
                nr[idx] = n[0, idx] * rx[idx] + n[1, idx] * ry[idx] + n[2, idx]
        else:
            n = flat[:, prim]
            nr = n[0] * rx + n[1] * ry + n[2]
        h, w = c.depth.shape
        return np.ascontiguousarray(n.T).reshape(h, w, 3), nr.reshape(h, w)

    def camera_points(self, c: Cast) -> np.ndarray:
        """(H, W, 3) float32 camera-frame points ``depth * ray`` (0 where no hit; z == depth exactly)."""
        return self._rays32.reshape(c.depth.shape + (3,)) * c.depth[..., None]

    # ------------------------------------------------------------------ exposure
    @property
    def exposure_ev(self) -> float:
        """The film exposure: fixed, or automatic-fixed from the reference frame (computed once)."""
        if self._exposure_ev is None:
            film = self.scene.film
            ref = min(max(film.auto_reference_frame, 0), len(self.scene.poses) - 1)
            c = self.cast(ref)
            lin = self._linear(ref, c, *self.camera_normals(ref, c))
            self._exposure_ev = auto_exposure_ev(lin, c.hit, film)
        return self._exposure_ev

    def _interp(self, tab: np.ndarray, c: Cast, ncomp: int) -> np.ndarray:
        """Barycentric interpolation of a per-face corner table (3 * ncomp, F + 1) at the hits: (H*W, ncomp)."""
        prim = np.where(c.hit, c.prim, np.uint32(tab.shape[1] - 1)).astype(np.intp).reshape(-1)
        uv = c.uv.reshape(-1, 2)
        a, b = uv[:, 0], uv[:, 1]
        w0 = 1 - a - b
        out = np.empty((len(prim), ncomp), dtype=np.float32)
        for j in range(ncomp):
            col = tab[j].take(prim) * w0
            col += tab[ncomp + j].take(prim) * a
            col += tab[2 * ncomp + j].take(prim) * b
            out[:, j] = col
        return out

    def albedo_per_pixel(self, i: int, c: Cast) -> np.ndarray:
        """The appearance function evaluated at every hit of frame ``i``: (H, W, 3) float32, 0 where no hit.

        World hit point = pose applied to ``depth * ray``; airway coordinates
        interpolated barycentrically from the vertices (wrap-free: cos and sin
        of the angle); noise fields every ``shading_stride`` pixels, bilinear.
        """
        from .texture import N_FIELDS, albedo_from_fields, noise_fields

        sc = self.scene
        tex = sc.material.texture
        h, w = c.depth.shape
        pose = sc.poses[i]
        k = self.config.shading_stride
        pc = self.camera_points(c)
        if k == 1:
            sel_hit = c.hit.reshape(-1)
            pts = pc.reshape(-1, 3)[sel_hit].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
            f = noise_fields(pts * 1000.0, tex, tex.seed)
        else:
            sub = pc[::k, ::k].astype(np.float64)
            gh, gw = sub.shape[:2]
            wp = sub.reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]
            coarse = noise_fields(wp * 1000.0, tex, tex.seed).reshape(gh, gw, N_FIELDS)
            coarse[~c.hit[::k, ::k]] = 0.0
            sel_hit = c.hit.reshape(-1)
            f = upsample_bilinear(coarse, h, w, k)[c.hit]
        air = None
        if self._airway_tab is not None:
            air = self._interp(self._airway_tab, c, 4)[sel_hit]
        out = np.zeros((h * w, 3), dtype=np.float32)
        out[sel_hit] = albedo_from_fields(f, tex, tex.seed, sc.material.base_color, air)
        return out.reshape(h, w, 3)

    def albedo(self, c: Cast) -> np.ndarray | None:
        """Per-pixel linear RGB albedo (H, W, 3) float32 of a textured scene (None when untextured).

        The vertex albedo (:meth:`Scene.vertex_albedo`) interpolated with the
        hit's barycentrics: ``(1-u-v) a0 + u a1 + v a2`` (Open3D's
        ``primitive_uvs``); 0 where no hit.
        """
        tab = self._albedo_tab
        if tab is None:
            return None
        prim = np.where(c.hit, c.prim, np.uint32(tab.shape[1] - 1)).astype(np.intp).reshape(-1)
        uv = c.uv.reshape(-1, 2)
        a, b = uv[:, 0], uv[:, 1]
        w0 = 1 - a - b
        out = np.empty((len(prim), 3), dtype=np.float32)
        for j in range(3):
            col = tab[j].take(prim) * w0
            col += tab[3 + j].take(prim) * a
            col += tab[6 + j].take(prim) * b
            out[:, j] = col
        return out.reshape(c.depth.shape + (3,))

    def _linear(self, i: int, c: Cast, normals: np.ndarray, n_dot_ray: np.ndarray) -> np.ndarray:
        light = self.scene.light
        mat = self.scene.material
        alb = self.albedo_per_pixel(i, c) if self._per_pixel else self.albedo(c)
        if np.any(np.asarray(light.offset_m) != 0):
            lin = shade_linear(self.camera_points(c), normals, c.hit, mat, light, alb)
            if self.config.direct_shadows:
                lin[self._in_shadow(i, c, normals)] = 0.0
        else:       # light at the camera: cos = -(n . ray) / |ray|, distance^2 = depth^2 |ray|^2
            cos = -n_dot_ray * self._inv_ray_len
            d2 = c.depth * c.depth * self._ray_len2
            lin = shade_coaxial(cos, d2, c.hit, mat, light, alb, cos_axis=self._inv_ray_len)
        if mat.interreflection > 0:
            lin += interreflection(lin, alb, c.depth, c.hit, mat)
        if self.config.indirect.bounces > 0:
            lin += self.indirect_radiance(i, c, alb, -n_dot_ray * self._inv_ray_len, normals)
        return lin

    def _in_shadow(self, i: int, c: Cast, normals: np.ndarray, eps_m: float = 1e-5) -> np.ndarray:
        """(H, W) bool: hits with mesh between them and the tip light (one shadow ray each, started ``eps_m``
        off the surface along the camera-facing normal)."""
        pose = np.asarray(self.scene.poses[self._index(i)], dtype=np.float64)
        R, t = pose[:3, :3], pose[:3, 3] - self.origin
        p = self.camera_points(c)[c.hit].astype(np.float64) + eps_m * normals[c.hit]
        o = p @ R.T + t
        d = (np.asarray(self.scene.light.offset_m, dtype=np.float64) - p) @ R.T
        out = self._rc.cast_rays(self._o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)),
                                 nthreads=self.config.nthreads)
        self.cast_count += 1
        mask = np.zeros(c.hit.shape, bool)
        mask[c.hit] = out["t_hit"].numpy() < 1.0 - 1e-4
        return mask

    @property
    def radiosity(self) -> Radiosity:
        """The mesh's precomputed light transport (built on first use; :mod:`room_pipeline.render.indirect`)."""
        if self._radiosity is None:
            t0 = time.perf_counter()
            sc = self.scene
            alb = sc.vertex_albedo()
            if alb is not None and self._per_pixel and self.config.transport_albedo == "area_mean":
                from .texture import vertex_albedo_area_mean

                alb = vertex_albedo_area_mean(sc.mesh.vertices, sc.mesh.faces, sc.material.texture,
                                              sc.material.base_color, sc.vertex_airway)
            self._radiosity = Radiosity(self._rc, sc.mesh.vertices, sc.mesh.faces, self.origin, sc.material,
                                        alb, self.config.indirect, self.config.nthreads)
            self.timings["indirect_build"] += time.perf_counter() - t0
        return self._radiosity

    def indirect_radiance(self, i: int, c: Cast, albedo: np.ndarray | None, cos_v: np.ndarray,
                          normals: np.ndarray) -> np.ndarray:
        """(H, W, 3) float32 radiance of the inter-reflected light at the hits of frame ``i`` (0 elsewhere).

        Diffuse: ``(1 - A(n.v)) albedo E_ind / pi`` with the vertices' indirect irradiance interpolated at the
        hit; glossy (``indirect.glossy``): ``A(n.v)`` times the radiance of the wall in the mirror direction
        (one reflection ray every ``indirect.glossy_stride`` pixels, bilinear).  ``cos_v`` (H, W): cosine
        between normal and view; ``normals`` (H, W, 3): camera-frame unit normals.
        """
        import cv2

        rad = self.radiosity
        t0 = time.perf_counter()
        pose = self.scene.poses[i]
        if self._rad_frame is None or self._rad_frame[0] != i:          # the sub-pixel samples reuse it
            self._rad_frame = (i, rad.frame(pose, self.scene.light))
        ed, e, lv = self._rad_frame[1]
        f = self.scene.mesh.faces
        tab = np.zeros((9, len(f) + 1), dtype=np.float32)
        tab[:, :-1] = e[f].reshape(-1, 9).T
        out = self._interp(tab, c, 3).reshape(c.depth.shape + (3,))
        a = specular_albedo_at(cos_v, self.scene.material)[..., None]          # layering: diffuse 1 - A(n.v)
        out *= (np.asarray(self.scene.material.base_color, dtype=np.float32) if albedo is None else albedo) * (1 - a)
        out *= np.float32(1 / np.pi)
        cfg = self.config.indirect
        if cfg.glossy:
            s = cfg.glossy_stride
            h, w = c.depth.shape
            sub = c.hit[::s, ::s]
            gh, gw = sub.shape
            R = pose[:3, :3]
            nrm = normals[::s, ::s][sub].astype(np.float64)
            d = (self.rays[::s, ::s][sub]) * self._inv_ray_len[::s, ::s][sub][:, None]
            r = d - 2 * np.einsum("ij,ij->i", d, nrm)[:, None] * nrm                 # mirror direction, camera frame
            p = self.camera_points(c)[::s, ::s][sub].astype(np.float64)
            org = (p + cfg.eps_m * nrm) @ R.T + pose[:3, 3]
            lm = rad.mirror_radiance(org, r @ R.T, lv)
            coarse = np.zeros((gh, gw, 3), dtype=np.float32)
            coarse[sub] = lm
            if s > 1:
                coarse = cv2.resize(coarse, (gw * s, gh * s), interpolation=cv2.INTER_LINEAR)[:h, :w]
            out += a * coarse
        out[~c.hit] = 0.0
        self.timings["indirect"] += time.perf_counter() - t0
        return out

    # ------------------------------------------------------------------ pixel filter
    def _filter_silhouettes(self, i: int, c: Cast, lin: np.ndarray) -> np.ndarray:
        """``lin`` (H, W, 3) with its silhouette pixels replaced by the mean radiance of ``edge_samples``^2
        sub-pixel rays at the pixel filter's quantiles (:mod:`room_pipeline.render.antialias`)."""
        from .antialias import filter_offsets, silhouette_pixels

        t0 = time.perf_counter()
        mask = silhouette_pixels(c.depth, c.hit, self.config.edge_depth_jump)
        yy, xx = np.nonzero(mask)
        if len(yy) == 0:
            return lin
        uv = np.stack([xx, yy], axis=1).astype(np.float64)[:, None, :] + filter_offsets(self.config.edge_samples)[None]
        dirs = self.scene.camera.rays_at(uv)                             # (N, m*m, 3), z = 1
        sub = self._sub_renderer(dirs)
        sc = sub._cast_grid(i)
        lin[mask] = sub._linear(i, sc, *sub.camera_normals(i, sc)).mean(axis=1)
        self.cast_count += sub.cast_count
        self.timings["edge_samples"] += time.perf_counter() - t0
        return lin

    def _sub_renderer(self, dirs: np.ndarray) -> "RaycastRenderer":
        """A view of this renderer (same BVH, tables, precomputed transport) whose 'image' is the (N, M) grid of
        camera-frame directions ``dirs`` (N, M, 3), z = 1; the appearance and glossy rays at every sample."""
        import copy

        if self.config.indirect.bounces > 0:
            self.radiosity                                               # built once, shared
        sub = copy.copy(self)
        sub.rays = np.asarray(dirs, dtype=np.float64)
        sub._rays32 = sub.rays.reshape(-1, 3).astype(np.float32)
        sub._rays_soa = tuple(np.ascontiguousarray(sub._rays32[:, k]) for k in range(3))
        len2 = np.einsum("nmi,nmi->nm", sub.rays, sub.rays)
        sub._ray_len2 = len2.astype(np.float32)
        sub._inv_ray_len = (1.0 / np.sqrt(len2)).astype(np.float32)
        sub.config = dataclasses.replace(self.config, shading_stride=1, edge_samples=0,
                                         indirect=dataclasses.replace(self.config.indirect, glossy_stride=1))
        sub._cache = collections.OrderedDict()
        sub.cast_count = 0
        return sub

    def _cast_grid(self, i: int) -> Cast:
        """The cast of this (sub-)renderer's own ray grid from pose ``i`` (not cached)."""
        shape = self.rays.shape[:2]
        out = self._cast_rays(self.scene.poses[i], self._rays32)
        depth, hit = self._depth_from(out)
        prim = out["primitive_ids"].numpy()
        prim[~hit] = _INVALID
        return Cast(depth=depth.reshape(shape), hit=hit.reshape(shape), prim=prim.reshape(shape),
                    uv=out["primitive_uvs"].numpy().reshape(shape + (2,)))

    # ------------------------------------------------------------------ render
    def render(self, frame_index: int, modalities: Iterable[str] = ("rgb", "depth")) -> dict[str, np.ndarray]:
        """Render the requested modalities of one frame (see the module docstring for the keys)."""
        mods = set(modalities)
        unknown = mods - MODALITIES
        if unknown:
            raise ValueError(f"unknown modalities {sorted(unknown)} (known: {sorted(MODALITIES)})")
        i = self._index(frame_index)
        film = self.scene.film
        ev = (film.ev(i, 0.0) if film.frame_ev is not None else self.exposure_ev) if "rgb" in mods else None
        c = self.cast(i)
        tm = self.timings
        res: dict[str, np.ndarray] = {"hit": c.hit}
        if "depth" in mods:
            res["depth"] = c.depth
        if "relative_depth" in mods:
            t0 = time.perf_counter()
            res["relative_depth"], res["relative_depth_range"] = relative_depth16(c.depth, c.hit)
            tm["relative_depth"] += time.perf_counter() - t0
        normals = None
        if mods & {"normals", "rgb", "point_cloud"}:
            t0 = time.perf_counter()
            normals, n_dot_ray = self.camera_normals(i, c)
            tm["normals"] += time.perf_counter() - t0
            if "normals" in mods:
                res["normals"] = normals
        if "rgb" in mods:
            t0 = time.perf_counter()
            lin = self._linear(i, c, normals, n_dot_ray)
            if self.config.edge_samples > 0:
                lin = self._filter_silhouettes(i, c, lin)
            lin *= np.float32(2.0 ** ev)
            if film.vignetting > 0:
                lin *= (self._inv_ray_len ** np.float32(film.vignetting))[..., None]
            res["rgb_linear"] = lin
            res["rgb"] = apply_response(lin, film)
            tm["rgb"] += time.perf_counter() - t0
        if "segmentation" in mods:
            t0 = time.perf_counter()
            # no-hit pixels carry prim 0xFFFFFFFF (cast()), which is -1 as int32 and past the label table's end
            res["primitive_ids"] = c.prim.view(np.int32).copy()
            if self._labels is None:
                res["segmentation"] = np.where(c.hit, 0, -1).astype(np.int32)
            else:
                res["segmentation"] = self._labels.take(np.minimum(c.prim, np.uint32(len(self._labels) - 1)))
            tm["segmentation"] += time.perf_counter() - t0
        if mods & {"point_cloud", "world_points"}:
            t0 = time.perf_counter()
            pc = self.camera_points(c)
            if "world_points" in mods:
                pose = self.scene.poses[i]
                wp = pc.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
                wp[~c.hit] = 0.0
                res["world_points"] = wp
            if "point_cloud" in mods:
                sel = self._select(c.hit)
                res["point_cloud"] = sel(pc)
                res["point_cloud_normals"] = sel(normals)
                res["point_cloud_pixels"] = sel(self._pixels)
                if "rgb" in res:
                    res["point_cloud_colors"] = sel(res["rgb"])
            tm["point_cloud"] += time.perf_counter() - t0
        if "flow" in mods:
            res["flow"], res["flow_valid"] = self._flow(i, c)
        return res

    @staticmethod
    def _select(hit: np.ndarray):
        """Row-major hit pixels of an (H, W, ...) array as (N, ...) (a reshape when everything is hit)."""
        if hit.all():
            return lambda a: np.ascontiguousarray(a).reshape((-1,) + a.shape[2:])
        return lambda a: a[hit]

    def _flow(self, i: int, c: Cast) -> tuple[np.ndarray, np.ndarray]:
        h, w = c.depth.shape
        if i + 1 >= len(self.scene.poses):
            return np.zeros((h, w, 2), np.float32), np.zeros((h, w), bool)
        c1 = self.cast(i + 1)
        t0 = time.perf_counter()
        poses = self.scene.poses
        rep = flowmod.reproject(c.depth, c.hit, self.scene.camera, poses[i], poses[i + 1], rays=self.rays)
        cfg = self.config
        if cfg.flow_occlusion == "depth":
            valid = flowmod.visible_in_depth(rep, c1.depth, c1.hit, cfg.occlusion_abs_tol_m, cfg.occlusion_rel_tol)
        else:
            valid = self.visible_by_raycast(rep, poses[i + 1])
        self.timings["flow"] += time.perf_counter() - t0
        return rep.flow, valid

    def visible_by_raycast(self, rep: flowmod.Reprojection, pose_t1: np.ndarray) -> np.ndarray:
        """Exact validity: cast from camera t+1 through ``p'``; visible when the hit depth matches ``z_{t+1}``."""
        cfg = self.config
        valid = np.zeros(rep.in_view.shape, dtype=bool)
        idx = np.flatnonzero(rep.in_view)
        if idx.size:
            d1, hit1 = self.depth_at(pose_t1, rep.uv1.reshape(-1, 2)[idx])
            z = rep.z1.reshape(-1)[idx]
            valid.reshape(-1)[idx] = hit1 & (np.abs(d1 - z) <= cfg.occlusion_abs_tol_m + cfg.occlusion_rel_tol * z)
        return valid

    def metadata(self) -> dict:
        """What a dataset writer records about this renderer (exposure, model, conventions)."""
        sc = self.scene
        return {"backend": "open3d_raycast", "config": dataclasses.asdict(self.config),
                "exposure_ev": self.exposure_ev, "film": dataclasses.asdict(sc.film),
                "material": dataclasses.asdict(sc.material), "light": dataclasses.asdict(sc.light),
                "texture": ("appearance function per shading point (render.texture)" if self._per_pixel else
                            "per-vertex albedo interpolated barycentrically" if self._albedo_tab is not None else None),
                "shading": "Lambert (1 - F) base/pi + GGX/Smith/Schlick specular, tip light "
                           "I = P/(4 pi) cos^spot_exponent, inverse-square or exponential falloff; "
                           + (f"indirect light: {self.config.indirect.bounces} diffuse bounces precomputed on the "
                              "mesh's vertices (render/indirect.py)" if self.config.indirect.bounces > 0 else
                              "no indirect light") + "; no subsurface",
                "camera": sc.camera.to_dict(), "conventions": metadata_block()}


def upsample_bilinear(coarse: np.ndarray, h: int, w: int, k: int) -> np.ndarray:
    """``coarse`` (gh, gw, C), the samples at every ``k``-th pixel, interpolated bilinearly at every pixel
    ``(y / k, x / k)`` of an (h, w) image, edges clamped: (h, w, C) float32.

    The same bytes as ``scipy.ndimage.map_coordinates(coarse[..., j], (y / k, x / k) as float32, order=1,
    mode='nearest')`` per channel (its weights ``1 - t, t`` in float64 from the float32 coordinate, each corner's
    value times the row weight, then the column weight, the four summed row-major; tested bit for bit in
    tests/test_raycast.py), faster (1.34x at load 2.7: ``python benchmarks/texture_speed.py``): the image is a
    regular grid, so each corner is one gather of columns on the coarse rows and one of rows, not a spline
    evaluation per pixel."""
    coarse = np.asarray(coarse)
    gh, gw = coarse.shape[:2]

    def axis(n: int, g: int):
        c = (np.arange(n) / k).astype(np.float32).astype(np.float64)
        i0 = np.floor(c).astype(np.intp)
        t = c - i0
        return np.minimum(i0, g - 1), np.minimum(i0 + 1, g - 1), 1.0 - t, t

    y0, y1, wy0, wy1 = axis(h, gh)
    x0, x1, wx0, wx1 = axis(w, gw)
    wa, wb = wy0[:, None], wy1[:, None]
    out = np.empty((h, w) + coarse.shape[2:], dtype=np.float32)
    for j in range(coarse.shape[2]):
        c = coarse[..., j].astype(np.float64)
        c0, c1 = c.take(x0, axis=1), c.take(x1, axis=1)
        t = (c0.take(y0, axis=0) * wa) * wx0
        t += (c1.take(y0, axis=0) * wa) * wx1
        t += (c0.take(y1, axis=0) * wb) * wx0
        t += (c1.take(y1, axis=0) * wb) * wx1
        out[..., j] = t
    return out


def relative_depth16(depth: np.ndarray, hit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised inverse depth as uint16 (see the module docstring) and [d_min, d_max] (float64 metres)."""
    hit = np.asarray(hit, dtype=bool)
    out = np.zeros(hit.shape, dtype=np.uint16)
    if not hit.any():
        return out, np.zeros(2)
    d = np.asarray(depth, dtype=np.float64)[hit]
    dmin, dmax = float(d.min()), float(d.max())
    inv = 1.0 / d
    span = 1.0 / dmin - 1.0 / dmax
    r = (inv - 1.0 / dmax) / span if span > 0 else np.ones_like(inv)
    out[hit] = (1 + np.rint(np.clip(r, 0.0, 1.0) * 65534)).astype(np.uint16)
    return out, np.array([dmin, dmax])


def decode_relative_depth16(rel: np.ndarray, depth_range: np.ndarray) -> np.ndarray:
    """Inverse of :func:`relative_depth16` up to quantisation: depth in metres, 0 where ``rel == 0``."""
    dmin, dmax = (float(x) for x in depth_range)
    r = np.asarray(rel, dtype=np.float64)
    if dmax <= 0:
        return np.zeros_like(r)
    inv = 1.0 / dmax + (r - 1) / 65534.0 * (1.0 / dmin - 1.0 / dmax)
    return np.where(r > 0, 1.0 / np.where(r > 0, inv, 1.0), 0.0)


def write_point_cloud(path: str | os.PathLike, out: dict[str, np.ndarray], frame_index: int | None = None,
                      pose: np.ndarray | None = None) -> None:
    """Binary little-endian PLY of a rendered ``point_cloud`` (camera frame, metres), atomically.

    Properties: float x, y, z; float nx, ny, nz (unit, camera frame, facing
    the camera); uchar red, green, blue when the RGB was rendered.  Header
    comments give the frame, the units and (optionally) the frame index and
    the camera-to-world pose to take the points to the world.
    """
    p, n = out["point_cloud"], out["point_cloud_normals"]
    vertex = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2]}
    if "point_cloud_colors" in out:
        col = out["point_cloud_colors"]
        vertex.update(red=col[:, 0], green=col[:, 1], blue=col[:, 2])
    comments = ["room-pipeline point cloud, one point per surface pixel (row-major)",
                "frame: OpenCV camera (x right, y down, z forward); units: m; z = planar depth",
                "normals: unit, camera frame, facing the camera"]
    if frame_index is not None:
        comments.append(f"frame_index {int(frame_index)}")
    if pose is not None:
        comments.append("camera_to_world " + " ".join(repr(float(x)) for x in np.asarray(pose).reshape(-1)))
    write_ply(path, vertex, comments=tuple(comments))
