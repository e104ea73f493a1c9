"""Stage `medial_axis`: lumen SDF -> centreline navigation graph.

Writes ``anatomy/medial_axis.ply`` (graph points: x, y, z in metres, radius in
metres, branch id, generation; edges along each branch polyline) and
``anatomy/centreline_graph.json`` (branches with parent, children, generation,
length, mean radius, points and radii).
"""
from __future__ import annotations

import numpy as np
from omegaconf import DictConfig

from ..anatomy.medial_axis import MedialAxisParams, extract_medial_axis
from ..config.compose import section
from ..io.atomic import write_json
from ..io.ply import write_ply
from ..io.volume import read_nifti_sdf
from .common import StageTimer, metadata, patient_paths, write_metrics


def outputs(cfg: DictConfig, patient: str) -> list:
    p = patient_paths(cfg, patient)
    return [p.medial_axis_ply, p.centreline_graph]


def graph_ply_arrays(graph) -> tuple[dict, np.ndarray]:
    """Vertex properties and polyline edges of a :class:`CentrelineGraph` for PLY."""
    cols, edges, offset = {"x": [], "y": [], "z": [], "radius": [], "branch": [], "generation": []}, [], 0
    for b in graph.branches:
        k = len(b.points)
        for name, i in (("x", 0), ("y", 1), ("z", 2)):
            cols[name].append(b.points[:, i])
        cols["radius"].append(b.radius)
        cols["branch"].append(np.full(k, b.id))
        cols["generation"].append(np.full(k, b.generation))
        edges.append(offset + np.stack([np.arange(k - 1), np.arange(1, k)], axis=1))
        offset += k
    vertex = {n: np.concatenate(v).astype(np.float64 if n in "xyz" else
                                          (np.float32 if n == "radius" else np.int32)) for n, v in cols.items()}
    return vertex, (np.concatenate(edges) if edges else np.zeros((0, 2), np.int64))


def run(cfg: DictConfig, patient: str) -> dict:
    params = MedialAxisParams.from_dict(section(cfg, "medial_axis"))
    paths = patient_paths(cfg, patient)
    with StageTimer() as timer:
        sdf = read_nifti_sdf(paths.sdf)
        res = extract_medial_axis(sdf, params)
    g = res.graph
    report = dict(res.report)
    timings = report.pop("timings", {})  # kept out of the data file: same inputs -> same bytes
    vertex, edges = graph_ply_arrays(g)
    write_ply(paths.medial_axis_ply, vertex, edges,
              comments=("room-pipeline medial axis (centreline graph points)", "units: m (x, y, z, radius)",
                        "frame: RAS+", "edges follow each branch polyline proximal -> distal"))
    doc = g.to_dict()
    doc["metadata"] = metadata("medial_axis", patient, cfg, ("medial_axis",), report=report)
    write_json(paths.centreline_graph, doc)
    gens = [b.generation for b in g.branches]
    metrics = {"n_branches": len(g.branches), "n_leaves": len(g.leaves()),
               "max_generation": int(max(gens)) if gens else 0,
               "total_length_mm": round(sum(b.length for b in g.branches) * 1e3, 3),
               "n_medial_points": int(len(res.medial_points)),
               **{f"time_{k}": v for k, v in timings.items()},
               "wall_time_s": round(timer.wall_s, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_metrics(paths, "medial_axis", metrics)
    return metrics
