"""The 3-D scene of one sequence: what is drawn (mesh, planned / simulated paths, cameras, scope backbones).

The scope is drawn as the simulation recorded it: ``simulation.json`` holds per frame the scope's backbone
(``frames[].backbone``, world m, entrance to tip: the shaft on the route, then the simulated body's link
vertices; :class:`room_pipeline.robot.simulation.SimResult`), so the report needs no robot model.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Mapping

import numpy as np

from ..catalog import RENDER_JSON, SIMULATION_JSON, TRAJECTORY_JSON, SequencePaths
from ..errors import InputError
from ..io.records import POSE_KEY, pose_track_from_doc
from .colour import pick_frames
from .common import read_json


@dataclasses.dataclass
class Scene3D:
    """What one 3-D view draws (world RAS+, metres); None / empty = absent."""

    mesh_vertices: np.ndarray | None = None
    mesh_faces: np.ndarray | None = None
    planned: np.ndarray | None = None          # (N, 3) planned camera positions
    simulated: np.ndarray | None = None        # (M, 3) simulated tip positions
    rendered: np.ndarray | None = None         # (K, 3) positions of the rendered cameras
    scopes: list = dataclasses.field(default_factory=list)   # (P, 3) backbone polylines
    tips: np.ndarray | None = None             # (S, 3) simulated tip positions at the scope frames
    scope_radius: float = 0.0025


def scope_backbones(simulation: Mapping, n_frames: int) -> tuple[list[np.ndarray], np.ndarray, list[int]]:
    """The recorded backbone polylines (P_i, 3), metres, of the simulated scope at ``n_frames`` evenly spaced
    simulation frames (the last included), their tips (S, 3) and the frame indices.
    Raises InputError when ``simulation.json`` records no backbone (made before it did: rerun simulate)."""
    try:
        sf = simulation["frames"]
        picks = pick_frames(len(sf), n_frames + 1)[1:] if n_frames > 0 and len(sf) > 1 else []
        picks = picks[-n_frames:] if n_frames else []
        lines = [np.asarray(sf[i]["backbone"], dtype=np.float64).reshape(-1, 3) for i in picks]
    except KeyError:
        raise InputError("simulation.json records no scope backbone (frames[].backbone; made by an older "
                         "simulate stage: rerun it)") from None
    except (TypeError, ValueError, IndexError) as exc:
        raise InputError(f"simulation.json: unreadable scope backbone ({exc})") from None
    if any(len(b) < 2 for b in lines):
        raise InputError("simulation.json: a recorded scope backbone has fewer than 2 points")
    return lines, np.array([b[-1] for b in lines]).reshape(-1, 3), list(picks)


def _track(path: Path, name: str, what: str, label: str, notes: list[str]):
    """``(document or None, its pose positions or None)`` of a trajectory/simulation file; a note when not drawn."""
    doc, why = read_json(path)
    try:
        if doc is not None:
            return doc, pose_track_from_doc(doc, POSE_KEY[name], path).positions
    except (KeyError, TypeError, ValueError, IndexError, InputError):
        doc, why = None, f"{name} has no {what}"
    notes.append(f"{label} not drawn: {why}")
    return doc, None


def sequence_scene(seq: Path, mesh, scope_frames: int) -> tuple[Scene3D, list[str]]:
    """The 3-D scene of one sequence and the caption lines saying what is drawn (and what is not)."""
    sp = SequencePaths(seq)
    sc = Scene3D()
    notes = []
    if mesh is not None:
        sc.mesh_vertices, sc.mesh_faces = mesh.vertices, mesh.faces
    _, sc.planned = _track(sp.trajectory, TRAJECTORY_JSON, "4x4 frame poses", "planned trajectory", notes)
    sim, sc.simulated = _track(sp.simulation, SIMULATION_JSON, "tip poses", "simulated tip path", notes)
    rend, _ = read_json(sp.render_json)
    if isinstance(rend, dict) and rend.get("frames"):
        try:
            sc.rendered = pose_track_from_doc(rend, POSE_KEY[RENDER_JSON], sp.render_json).positions
        except (KeyError, TypeError, ValueError, IndexError, InputError):
            notes.append("rendered cameras not drawn: render.json frames lack 4x4 poses")
    if scope_frames and sim is not None:
        try:
            sc.scopes, sc.tips, picks = scope_backbones(sim, scope_frames)
            robot, _ = read_json(sp.robot_config)
            diam = ((robot or {}).get("scope") or {}).get("outer_diameter")
            if isinstance(diam, (int, float)) and diam > 0:
                sc.scope_radius = 0.5 * float(diam)
            notes.append("scope (tube, outer diameter %.1f mm) at simulation frames %s, as simulated (the backbone "
                         "simulation.json records)" % (2e3 * sc.scope_radius, ", ".join(map(str, picks))))
        except InputError as exc:
            notes.append(f"scope not drawn: {exc}")
    elif scope_frames:
        notes.append("scope not drawn: it needs simulation.json")
    return sc, notes
