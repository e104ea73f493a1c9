"""Stage `simulate`: drive the PyBullet scope along a sequence's planned trajectory.

Writes ``<patient>/<sequence>/metadata/robot_config.json`` (model parameters),
``simulation.json`` (per 10 Hz frame: actual tip camera pose, commanded and
actual q, contact force, penetration, tracking error) and
``simulated_tum.txt`` (the actual camera poses in TUM format, which rendering
uses).

The wall is ``anatomy/collision_model.obj``, the mesh stage's decimated copy of
the render mesh (its measured distance to it is copied into ``robot_config.json``),
open proximally (:mod:`room_pipeline.robot.sequence_sim`).
"""
from __future__ import annotations

from omegaconf import DictConfig

from ..catalog import split_key
from ..config.compose import section
from ..errors import InputError
from ..io.atomic import write_json, write_text
from ..io.mesh import read_obj
from ..io.tum import tum_text
from ..robot.kinematics import ScopeGeometry
from ..robot.sim_params import SimParams
from ..robot.simulation import check_inputs, robot_config, simulate
from ..robot.sequence_sim import data_report, open_entrance, read_inputs, sim_metrics
from .common import StageTimer, metadata, patient_paths, read_json, write_metrics


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    s = patient_paths(cfg, patient).seq(sequence)
    return [s.robot_config, s.simulation, s.simulated_tum]


def run(cfg: DictConfig, key: str) -> dict:
    patient, sequence = split_key(key)
    params = SimParams.from_dict(section(cfg, "simulate"))
    geometry = ScopeGeometry()
    paths = patient_paths(cfg, patient)
    sp = paths.seq(sequence)
    with StageTimer() as timer:
        traj, root_radius = read_inputs(sp.trajectory, paths.centreline_graph, key)
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
    sim_doc = res.to_dict()
    sim_doc["report"] = data_report(res.report, n_dropped)
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
    metrics = {**sim_metrics(len(res.timestamps), res.report),
               "wall_time_s": round(timer.wall_s, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_metrics(paths, "simulate", metrics, sequence=sequence)
    return metrics
