"""Stage `mesh`: SDF zero level -> watertight lumen surface ``lung_model.obj`` (metres).

Also writes ``collision_model.obj``, the simulate stage's decimated copy of it
(``room_pipeline.anatomy.collision``; its measured error is in ``mesh_metadata.json``).

With ``mesh.tetrahedralize: true`` a tetrahedral volume mesh of the lumen is
written to ``anatomy/volume_mesh/lung_model_tet.npz`` (arrays ``vertices`` in
metres and ``tetrahedra``); ``volume_mesh/info.json`` always says whether it was made.
"""
from __future__ import annotations

import numpy as np
from omegaconf import DictConfig

from ..anatomy.mesh import MeshParams, extract_surface
from ..config.compose import section
from ..io.atomic import write_json, write_with
from ..io.mesh import write_obj
from ..io.volume import read_nifti_sdf
from .common import StageTimer, metadata, patient_paths, write_metrics


def outputs(cfg: DictConfig, patient: str) -> list:
    p = patient_paths(cfg, patient)
    return [p.mesh, p.collision_mesh, p.mesh_metadata, p.volume_mesh]


def run(cfg: DictConfig, patient: str) -> dict:
    params = MeshParams.from_dict(section(cfg, "mesh"))
    paths = patient_paths(cfg, patient)
    with StageTimer() as timer:
        sdf = read_nifti_sdf(paths.sdf)
        res = extract_surface(sdf, params)
    meta = metadata("mesh", patient, cfg, ("mesh",), report=res.report)
    write_obj(paths.mesh, res.mesh, header=f"room-pipeline lung_model (lumen surface) of {patient}\n"
                                           "normals point from air into tissue")
    write_obj(paths.collision_mesh, res.collision,
              header=f"room-pipeline collision_model (scope simulation copy of lung_model) of {patient}\n"
                     "normals point from air into tissue")
    write_json(paths.mesh_metadata, meta)
    if res.tets is not None:
        verts, tets = res.tets

        def _save(tmp):
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, vertices=np.asarray(verts, np.float64), tetrahedra=np.asarray(tets, np.int64))

        write_with(paths.tet_mesh, _save)
        write_json(paths.volume_mesh_info, {"tetrahedralized": True, "n_tetrahedra": int(len(tets)),
                                          "n_vertices": int(len(verts)), "units": "m"})
    else:
        write_json(paths.volume_mesh_info, {"tetrahedralized": False,
                                          "reason": "mesh.tetrahedralize is false"})
    metrics = {k: v for k, v in res.report.items() if isinstance(v, (int, float, bool))}
    col = res.report.get("collision", {})
    metrics.update(collision_faces=col.get("faces"), collision_error_max_mm=round(col.get("error_max_mm", 0.0), 4))
    metrics.update(wall_time_s=round(timer.wall_s, 3), peak_rss_mb=round(timer.peak_rss_mb(), 1))
    write_metrics(paths, "mesh", metrics)
    return metrics
