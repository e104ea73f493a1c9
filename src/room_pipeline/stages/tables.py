"""Stage `tables`: every configured patient x sequence -> the report tables (paper Tables I-III) in ``reports/``.

Not per patient: ``room stage tables --patient all`` (the key may also be one
configured patient id, to tabulate only that patient).  Reads, where present,
``<output_dir>/evaluation/<patient>/<sequence>/pose.json`` (stage
`evaluate_pose`), ``.../evaluation/depth.json`` and
``<output_dir>/evaluation/<patient>/depth_finetune.json`` (the depth stages);
a missing file gives a "not run" row, never an error.

Table III's ``other_anatomy`` rows come from the `evaluate_depth` records of
the patients other than ``depth.cnn.checkpoint_patient`` (or those of
``depth.train.eval_patients``): ``cnn_pretrained`` is "before", ``cnn`` (the
checkpoint fine-tuned on the training patient) is "after", both median-scaled
per sequence like the other Table III sets; mean over each patient's
sequences, then over patients.

Writes into ``evaluate.tables.output_dir`` (default ``reports/``):
``table_1_pose.{md,tex,csv}``, ``table_2_depth.{md,tex,csv}``,
``table_3_finetune.{md,tex,csv}``, ``pose_speed_accuracy.csv`` (time per frame
against accuracy, for ``dvc plots``) and ``metrics.json`` (for ``dvc metrics
show``).  Same inputs -> same bytes (no time stamps).
"""
from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from ..catalog import SPEED_ACCURACY_CSV, TABLES_METRICS_JSON
from ..errors import ConfigError
from ..evaluate.pose_eval import PoseEvalParams
from ..evaluate.reports import (TABLES, TablesParams, build_tables, other_anatomy_records, read_depth_files,
                                read_pose_files, report_files)
from ..io.atomic import write_json, write_text
from ..io.metrics import write_metrics_file


def _evaluate_section(cfg: DictConfig) -> dict:
    ev = cfg.get("evaluate")
    if ev is None:
        raise ConfigError("config has no section 'evaluate' (conf/evaluate/default.yaml)")
    return OmegaConf.to_container(ev, resolve=True) if isinstance(ev, DictConfig) else dict(ev)


def _targets(cfg: DictConfig, key: str) -> tuple[list[str], list[str]]:
    patients = sorted(cfg.get("patients") or {})
    if key not in ("all", "", None):
        if key not in patients:
            raise ConfigError(f"tables: --patient must be 'all' or a configured patient, got '{key}' "
                              f"(patients: {', '.join(patients) or 'none'})")
        patients = [key]
    return patients, [str(s) for s in (cfg.get("sequences") or [])]


def outputs(cfg: DictConfig, key: str) -> list:
    """The tables, then (last) the dataset's DVC metrics file."""
    p = TablesParams.from_dict(_evaluate_section(cfg).get("tables"))
    out = Path(p.output_dir)
    return ([out / f"{t}.{ext}" for t in TABLES for ext in ("md", "tex", "csv")]
            + [out / SPEED_ACCURACY_CSV, out / TABLES_METRICS_JSON])


def run(cfg: DictConfig, key: str) -> dict:
    ev = _evaluate_section(cfg)
    p = TablesParams.from_dict(ev.get("tables"))
    patients, sequences = _targets(cfg, key)
    output_dir = Path(cfg.output_dir)
    pose_docs = read_pose_files(output_dir, patients, sequences)
    depth_by_patient, finetune_docs = read_depth_files(output_dir, patients, sequences)
    depth_docs = [d for pat in patients for d in depth_by_patient.get(pat, [])]
    n_finetune = len(finetune_docs)
    if finetune_docs:       # the fine-tuning ran: add its other-anatomy evaluation (module docstring)
        finetune_docs = finetune_docs + other_anatomy_records(cfg, depth_by_patient)
    order = tuple(PoseEvalParams.from_dict(ev.get("pose")).methods)     # the pose table's row order
    tables = build_tables(pose_docs, depth_docs, finetune_docs, p.digits, order)
    counts = {"patients": len(patients), "sequences": len(patients) * len(sequences),
              "pose_json": len(pose_docs), "depth_json": len(depth_docs), "depth_finetune_json": n_finetune}
    for name, content in report_files(tables, counts).items():    # metrics.json: timings go beside it
        write = write_metrics_file if name == TABLES_METRICS_JSON else write_json if isinstance(content, dict) else write_text
        write(Path(p.output_dir) / name, content)
    return counts
