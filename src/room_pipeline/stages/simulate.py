"""Stage `simulate`: drive the PyBullet scope along a sequence's planned trajectory.

Writes ``<patient>/<sequence>/metadata/robot_config.json`` (model parameters),
``simulation.json`` (per 10 Hz frame: actual tip camera pose, commanded and
actual q, contact force, penetration, tracking error) and
``simulated_tum.txt`` (the actual camera poses in TUM format, which rendering
uses).

The wall is ``anatomy/collision_model.obj``, the mesh stage's decimated copy of
the render mesh (its measured distance to it is copied into ``robot_config.json``).

Modelling choice: the airway is open proximally.  The lumen mesh is closed at
its top (the trachea entry of the phantom or the volume border of a CT), but a
real airway continues to the larynx, and the scope's bending segment (50 mm)
reaches above the first pose.  Triangles behind the plane of the first pose
and within three root radii of the path axis are left out of the collision
mesh; the count is recorded.
"""
from __future__ import annotations

import numpy as np
from omegaconf import DictConfig

from ..catalog import split_key
from ..config.compose import section
from ..errors import InputError
from ..io.atomic import write_json, write_text
from ..io.mesh import Mesh, read_obj
from ..io.records import pose_track
from ..io.tum import tum_text
from ..robot.kinematics import ScopeGeometry
from ..robot.pybullet_sim import SimParams, check_inputs, robot_config, simulate
from .common import StageTimer, metadata, patient_paths, read_json, write_metrics

#: report entries that depend on the machine, kept out of the data files (they go to metrics)
_TIMING_KEYS = ("wall_time_s", "realtime_factor")


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    s = patient_paths(cfg, patient).seq(sequence)
    return [s.robot_config, s.simulation, s.simulated_tum]


def open_entrance(mesh: Mesh, start: np.ndarray, tangent: np.ndarray, radius: float) -> tuple[Mesh, int]:
    """Drop the triangles proximal to the start plane near the path axis (see module docstring)."""
    c = mesh.vertices[mesh.faces].mean(axis=1)
    rel = c - start
    along = rel @ tangent
    off_axis = np.linalg.norm(rel - along[:, None] * tangent, axis=1)
    drop = (along < 0) & (off_axis < 3.0 * radius)
    return Mesh(mesh.vertices, mesh.faces[~drop]), int(drop.sum())


def _read_inputs(trajectory_json, graph_json, key: str):
    """The planned trajectory (timestamps, poses, arclength) and the root branch's radius; a missing or
    malformed file is one :class:`InputError` line naming it."""
    path = trajectory_json
    try:
        traj = pose_track(path, read_json(path))
        if traj.arclength is None:
            raise ValueError("frames without 'arclength'")
        path = graph_json
        graph = read_json(path)
        root_radius = float(next(b for b in graph["branches"] if b["parent"] == -1)["mean_radius"])
    except StopIteration:
        raise InputError(f"simulate {key}: {path} has no root branch (parent -1)") from None
    except (OSError, ValueError, KeyError, TypeError, IndexError, InputError) as exc:
        raise InputError(f"simulate {key}: cannot read {path} ({type(exc).__name__}: "
                         f"{' '.join(str(exc).split())})") from None
    if not (np.isfinite(root_radius) and root_radius > 0):
        raise InputError(f"simulate {key}: {graph_json}: root branch radius must be > 0, got {root_radius}")
    return traj, root_radius


def run(cfg: DictConfig, key: str) -> dict:
    patient, sequence = split_key(key)
    params = SimParams.from_dict(section(cfg, "simulate"))
    geometry = ScopeGeometry()
    paths = patient_paths(cfg, patient)
    sp = paths.seq(sequence)
    with StageTimer() as timer:
        traj, root_radius = _read_inputs(sp.trajectory, paths.centreline_graph, key)
        try:
            wall = read_obj(paths.collision_mesh)
        except (OSError, ValueError, IndexError) as exc:
            raise InputError(f"simulate {key}: cannot read the collision mesh {paths.collision_mesh} "
                             f"({type(exc).__name__}: {' '.join(str(exc).split())})") from None
        try:
            check_inputs(traj, wall)
        except InputError as exc:
            raise InputError(f"{key}: {exc} ({paths.collision_mesh}, {sp.trajectory})") from None
        mesh, n_dropped = open_entrance(wall, traj.poses[0, :3, 3], traj.poses[0, :3, 2], root_radius)
        try:
            res = simulate(traj, mesh, params, geometry)
        except InputError as exc:
            raise InputError(f"{key}: {exc}") from None
    report = {k: v for k, v in res.report.items() if k not in _TIMING_KEYS}
    if isinstance(report.get("mesh"), dict):
        report["mesh"] = {k: v for k, v in report["mesh"].items() if k != "build_time_s"}
    report["entrance_faces_removed"] = n_dropped
    report["unstable_runs"] = [{k: v for k, v in u.items() if k not in _TIMING_KEYS} for u in report["unstable_runs"]]
    sim_doc = res.to_dict()
    sim_doc["report"] = report
    sim_doc["metadata"] = metadata("simulate", patient, cfg, ("simulate",), sequence=sequence)
    mesh_meta = read_json(paths.mesh_metadata) if paths.mesh_metadata.is_file() else {}
    collision = mesh_meta.get("report", {}).get("collision")
    write_json(sp.robot_config, {**robot_config(params, geometry),
                                               "collision_mesh": {"file": paths.collision_mesh.name,
                                                                  "units": "m; error bounds mm", **(collision or {})},
                                               "metadata": metadata("simulate", patient, cfg, ("simulate",))})
    write_json(sp.simulation, sim_doc)
    write_text(sp.simulated_tum,
               tum_text(res.timestamps, res.tip_poses, "simulated camera-to-world, OpenCV camera, world RAS+, m, s"))
    r = res.report
    metrics = {"frames": int(len(res.timestamps)),
               "tracking_error_median_mm": round(r["tracking_error_mm"]["median"], 4),
               "tracking_error_max_mm": round(r["tracking_error_mm"]["max"], 4),
               "view_error_median_deg": round(r["tracking_error_deg"]["median"], 4),
               "view_error_max_deg": round(r["tracking_error_deg"]["max"], 4),
               "camera_roll_straight_stretch_max_deg": round(r["camera_roll_deg"]["straight_stretch_change_max"], 4),
               "contact_force_max_n": round(r["contact_force_n"]["max"], 6),
               "penetration_max_mm": round(r["penetration_mm"]["max"], 6),
               "time_step_s": r["time_step_s"], "unstable_runs": len(r["unstable_runs"]),
               "realtime_factor": round(r["realtime_factor"], 3),
               "wall_time_s": round(timer.wall_s, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_metrics(paths, f"simulate_{sequence}", metrics)
    return metrics
