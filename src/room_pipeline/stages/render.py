"""Stage `render`: a sequence's camera poses + the lumen mesh -> the ROOM modalities.

Writes into ``<patient>/<sequence>/``: ``rgb/frame_NNNN.png`` (8-bit sRGB),
``depth/frame_NNNN.exr`` (planar z, float32 metres, channel Y, 0 = no hit),
``relative_depth/frame_NNNN.png`` (16-bit normalised inverse depth, 0 = no hit;
per-frame [d_min, d_max] in ``metadata/render.json``),
``surface_normals/frame_NNNN.exr`` (unit normals in the OpenCV camera frame,
facing the camera; channels R, G, B = x, y, z; 0 = no hit),
``optical_flow/frame_NNNN.flo`` (Middlebury, forward t -> t+1, pixels) with
``optical_flow/valid_NNNN.png`` (255 = valid: visible at t+1, inside, not
occluded), ``point_clouds/frame_NNNN.ply`` (camera frame, metres, normals,
colour), ``segmentation/frame_NNNN.png`` (uint16: airway branch id + 1, 0 =
no hit) with ``segmentation/legend.json`` (label -> branch id, generation),
``calibration/camera_params.json`` and ``metadata/render.json`` (renderer,
exposure, per-frame source index, timestamp, camera-to-world pose).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np
from omegaconf import DictConfig
from scipy.spatial import cKDTree

from ..anatomy.centreline import CentrelineGraph
from ..config.compose import section
from ..config.params import params_from_dict
from ..conventions import MM, metadata_block
from ..errors import ConfigError, InputError
from ..io.atomic import write_json
from ..io.images import write_exr, write_flo, write_png8, write_png16
from ..io.mesh import Mesh, read_obj
from ..render.camera import CameraIntrinsics
from ..progress import progress
from ..render.scene import Film, Scene, TipLight, TissueMaterial
from ..render.texture import MucosaTexture
from .common import StageTimer, metadata, patient_paths, read_json, write_metrics
from .trajectory import split_key

#: modality -> output folder (the ROOM layout)
FOLDERS = {"rgb": "rgb", "depth": "depth", "relative_depth": "relative_depth", "normals": "surface_normals",
           "flow": "optical_flow", "point_cloud": "point_clouds", "segmentation": "segmentation"}


@dataclasses.dataclass(frozen=True)
class RenderParams:
    """Keys of ``conf/render/default.yaml`` (see its comments for units)."""

    backend: str = "raycast"
    poses: str = "planned"
    modalities: tuple = ("rgb", "depth", "relative_depth", "normals", "flow", "segmentation")
    frame_stride: int = 1
    max_frames: int | None = None
    width: int = 600
    height: int = 600
    fov_deg: float = 85.0
    near_mm: float = 0.1
    far_mm: float = 500.0
    base_color: tuple = (0.80, 0.38, 0.32)
    roughness: float = 0.35
    specular: float = 0.5
    light_power_w: float = 0.02
    light_radius_mm: float = 0.5
    exposure_ev: float | None = None
    auto_exposure_target: float = 0.8
    texture: dict = dataclasses.field(default_factory=dict)
    cycles_samples: int = 16
    cycles_denoise: bool = True

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "RenderParams":
        p = params_from_dict(cls, d, "render")
        if p.backend not in ("raycast", "cycles"):
            raise ConfigError(f"render.backend must be 'raycast' or 'cycles', got {p.backend!r}")
        if p.poses not in ("planned", "simulated"):
            raise ConfigError(f"render.poses must be 'planned' or 'simulated', got {p.poses!r}")
        bad = set(p.modalities) - set(FOLDERS)
        if bad:
            raise ConfigError(f"render.modalities: unknown {sorted(bad)} (known: {sorted(FOLDERS)})")
        if p.frame_stride < 1 or p.width < 8 or p.height < 8 or not 1.0 < p.fov_deg < 170.0:
            raise ConfigError("render: frame_stride >= 1, width/height >= 8 and 1 < fov_deg < 170 required")
        texture_params(p.texture)
        return p


def texture_params(d: Mapping[str, Any] | None) -> MucosaTexture:
    """The ``render.texture`` section as a :class:`MucosaTexture` (unknown key or bad value: ConfigError)."""
    if d is not None and not isinstance(d, Mapping):
        raise ConfigError(f"render.texture must be a mapping, got {d!r}")
    try:
        return params_from_dict(MucosaTexture, d, "render.texture")
    except ValueError as e:
        raise ConfigError(str(e).splitlines()[0]) from None


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    seq = patient_paths(cfg, patient).sequence(sequence)
    return [seq / f for f in FOLDERS.values()] + [seq / "calibration", seq / "metadata" / "render.json"]


def face_labels(mesh: Mesh, graph: CentrelineGraph) -> tuple[np.ndarray, dict]:
    """Per-face airway branch id (nearest centreline point to the face centroid) and the legend."""
    pts, _, bid = graph.all_points()
    if len(pts) == 0:
        return np.zeros(mesh.n_faces, np.int32), {}
    _, idx = cKDTree(pts).query(mesh.vertices[mesh.faces].mean(axis=1))
    labels = bid[idx].astype(np.int32)
    legend = {str(b.id + 1): {"branch_id": b.id, "generation": b.generation, "parent": b.parent}
              for b in graph.branches}
    return labels, legend


def load_poses(meta_dir, which: str) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps, camera-to-world poses) of the planned or the simulated sequence."""
    if which == "simulated":
        doc = read_json(meta_dir / "simulation.json")
        return (np.array([f["timestamp"] for f in doc["frames"]]), np.array([f["tip_pose"] for f in doc["frames"]]))
    doc = read_json(meta_dir / "trajectory.json")
    return np.array([f["timestamp"] for f in doc["frames"]]), np.array([f["pose"] for f in doc["frames"]])


class _Renderers:
    """The fast ray caster for every geometric modality; with backend 'cycles' the RGB comes from Cycles.

    The product writes geometric depth, normals and flow in both cases: Cycles' passes agree with them
    (depth 2e-5 relative, flow 0.007 px; tests/test_blender.py) but its vector pass blends the two
    surfaces at silhouettes, where the geometric flow is exact.
    """

    def __init__(self, scene: Scene, p: RenderParams) -> None:
        from ..render.raycast import RaycastRenderer

        self.raycast = RaycastRenderer(scene)
        self.cycles = None
        if p.backend == "cycles":
            from ..render.blender import CyclesRenderer, CyclesSettings

            self.cycles = CyclesRenderer(scene, CyclesSettings.from_dict({"samples": p.cycles_samples,
                                                                         "denoise": p.cycles_denoise}))

    def render(self, i: int, mods: set) -> dict:
        if self.cycles is None:
            return self.raycast.render(i, mods)
        from ..render.blender import linear_to_srgb8

        out = self.raycast.render(i, mods - {"rgb"})
        if "rgb" in mods:
            out["rgb"] = linear_to_srgb8(self.cycles.render(i, ("rgb",))["rgb"])
            if "point_cloud" in out:
                out["point_cloud_colors"] = out["rgb"][out["hit"]]
        return out

    def metadata(self) -> dict:
        meta = self.raycast.metadata()
        if self.cycles is not None:
            meta = {"rgb": {"backend": "blender_cycles", "exposure_ev": self.cycles.exposure_ev,
                            "settings": dataclasses.asdict(self.cycles.settings)},
                    "geometry": meta}
        return meta

    def close(self) -> None:
        if self.cycles is not None:
            self.cycles.close()


def run(cfg: DictConfig, key: str) -> dict:
    patient, sequence = split_key(key)
    p = RenderParams.from_dict(section(cfg, "render"))
    paths = patient_paths(cfg, patient)
    seq = paths.sequence(sequence)
    with StageTimer() as timer:
        ts, poses = load_poses(paths.sequence_metadata(sequence), p.poses)
        src = np.arange(0, len(ts), p.frame_stride)
        if p.max_frames is not None:
            src = src[: int(p.max_frames)]
        if len(src) == 0:
            raise InputError(f"{sequence}: no poses to render")
        mesh = read_obj(paths.mesh)
        labels, legend = face_labels(mesh, CentrelineGraph.from_dict(read_json(paths.centreline_graph)))
        cam = CameraIntrinsics.from_fov(p.width, p.height, p.fov_deg, p.near_mm * MM, p.far_mm * MM)
        scene = Scene(mesh, cam, poses[src], ts[src],
                      material=TissueMaterial(base_color=tuple(p.base_color), roughness=p.roughness,
                                              specular=p.specular, texture=texture_params(p.texture)),
                      light=TipLight(power_w=p.light_power_w, radius_m=p.light_radius_mm * MM),
                      film=Film(exposure_ev=p.exposure_ev, auto_target=p.auto_exposure_target), face_labels=labels)
        renderer = _Renderers(scene, p)
        mods = set(p.modalities)
        for folder in FOLDERS.values():
            (seq / folder).mkdir(parents=True, exist_ok=True)
        frames, n_valid_flow, n_hit = [], [], []
        for i in progress(range(len(src)), len(src), f"render {key}"):
            out = renderer.render(i, mods)
            name = f"frame_{i:04d}"
            hit = out["hit"]
            n_hit.append(float(hit.mean()))
            rec = {"index": i, "source_index": int(src[i]), "timestamp": float(ts[src[i]]),
                   "pose": np.round(poses[src[i]], 12).tolist(), "hit_fraction": float(hit.mean())}
            if "rgb" in out:
                write_png8(seq / "rgb" / f"{name}.png", out["rgb"])
            if "depth" in out:
                write_exr(seq / "depth" / f"{name}.exr", np.where(hit, out["depth"], 0).astype(np.float32),
                          channels=("Y",), attributes={"units": "m", "quantity": "planar z depth, 0 = no hit"})
            if "relative_depth" in out:
                write_png16(seq / "relative_depth" / f"{name}.png", out["relative_depth"])
                rec["relative_depth_range_m"] = [float(x) for x in out["relative_depth_range"]]
            if "normals" in out:
                write_exr(seq / "surface_normals" / f"{name}.exr", out["normals"].astype(np.float32),
                          attributes={"frame": "OpenCV camera; R,G,B = x,y,z; unit; 0 = no hit"})
            if "flow" in out:
                write_flo(seq / "optical_flow" / f"{name}.flo", out["flow"].astype(np.float32))
                write_png8(seq / "optical_flow" / f"valid_{i:04d}.png",
                           (out["flow_valid"].astype(np.uint8) * 255))
                n_valid_flow.append(float(out["flow_valid"].mean()))
            if "point_cloud" in out:
                from ..render.raycast import write_point_cloud

                write_point_cloud(seq / "point_clouds" / f"{name}.ply", out, i, poses[src[i]])
            if "segmentation" in out:
                write_png16(seq / "segmentation" / f"{name}.png", (out["segmentation"] + 1).astype(np.uint16))
            frames.append(rec)
        renderer.close()
    if "segmentation" in mods:
        write_json(seq / "segmentation" / "legend.json",
                   {"encoding": "uint16 PNG: label = airway branch id + 1, 0 = no hit",
                    "branch_ids": "centreline_graph.json ids", "labels": legend})
    write_json(seq / "calibration" / "camera_params.json", cam.to_dict())
    write_json(seq / "metadata" / "render.json", {
        "renderer": renderer.metadata(),
        "poses": p.poses, "modalities": sorted(mods), "frames": frames,
        "flow": "forward t -> t+1 in pixels (u right, v down); the last frame has zero flow and no valid pixel",
        "conventions": metadata_block(),
        "metadata": metadata("render", patient, cfg, ("render",), sequence=sequence)})
    metrics = {"frames": len(frames), "hit_fraction_mean": round(float(np.mean(n_hit)), 6),
               "flow_valid_fraction_mean": round(float(np.mean(n_valid_flow)), 6) if n_valid_flow else None,
               "wall_time_s": round(timer.wall_s, 3), "frames_per_s": round(len(frames) / timer.wall_s, 3),
               "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_metrics(paths, f"render_{sequence}", metrics)
    return metrics
