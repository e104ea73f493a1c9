"""Stage `tables`: every configured patient x sequence -> the report tables (paper Tables I-III) in ``reports/``.

Not per patient: ``room stage tables --patient all`` (the key may also be one
configured patient id, to tabulate only that patient).  Reads, where present,
``<output_dir>/evaluation/<patient>/<sequence>/pose.json`` (stage
`evaluate_pose`), ``.../evaluation/depth.json`` and
``<output_dir>/evaluation/<patient>/depth_finetune.json`` (the depth stages);
a missing file gives a "not run" row, never an error.

Writes into ``evaluate.tables.output_dir`` (default ``reports/``):
``table_1_pose.{md,tex,csv}``, ``table_2_depth.{md,tex,csv}``,
``table_3_finetune.{md,tex,csv}``, ``pose_speed_accuracy.csv`` (time per frame
against accuracy, for ``dvc plots``) and ``metrics.json`` (for ``dvc metrics
show``).  Same inputs -> same bytes (no time stamps).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Mapping

from omegaconf import DictConfig, OmegaConf

from ..config.params import params_from_dict
from ..errors import ConfigError, InputError
from ..evaluate import paper
from ..evaluate.tables import depth_table, finetune_table, pose_table, speed_accuracy_csv
from ..io.atomic import write_json, write_text
from ..paths import PatientPaths
from .common import _finite, round_floats

TABLES = ("table_1_pose", "table_2_depth", "table_3_finetune")
#: per-patient fine-tuning records, in order of preference (metrics/<name>.json)


@dataclasses.dataclass(frozen=True)
class TablesParams:
    """Keys of ``evaluate.tables`` in ``conf/evaluate/default.yaml``."""

    output_dir: str = "reports"
    digits: int = 2

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "TablesParams":
        p = params_from_dict(cls, d, "evaluate.tables")
        if not 0 <= p.digits <= 6 or not p.output_dir:
            raise ConfigError("evaluate.tables: 0 <= digits <= 6 and a non-empty output_dir required")
        return p


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
    p = TablesParams.from_dict(_evaluate_section(cfg).get("tables"))
    out = Path(p.output_dir)
    return ([out / f"{t}.{ext}" for t in TABLES for ext in ("md", "tex", "csv")]
            + [out / "pose_speed_accuracy.csv", out / "metrics.json"])


def _read(path: Path) -> Any:
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not readable JSON ({exc})") from None


def read_depth_files(output_dir: Path, patients: list[str], sequences: list[str]) -> tuple[list[dict], list[dict]]:
    """The depth stages' records: (per-sequence ``evaluation/depth.json`` docs, per-patient ``depth_finetune.json``).

    The one place that knows the other stages' file layout and format (adjust here if it changes):
    ``depth.json`` = {"methods": {name: {"available", "reason", "L1_mm", "AbsRel", "RMSE_mm", "delta1", ...,
    "n_frames", "seconds_per_frame"}}, "units": {...}}; ``depth_finetune.json`` = {"datasets": {name:
    {"before": {metrics}, "after": {metrics}}}}.  ``delta1`` is taken as a fraction unless ``units.delta1``
    mentions %, in which case it is converted to a fraction here.  The fine-tuning record is
    ``<output_dir>/evaluation/<patient>/depth_finetune.json`` (written by `train_depth`, with per-dataset
    ``available`` / ``reason``).
    """
    depth, finetune = [], []
    for pat in patients:
        paths = PatientPaths(output_dir, pat)
        for seq in sequences:
            f = paths.evaluation(seq) / "depth.json"
            if f.is_file():
                doc = _read(f)
                if "%" in str((doc.get("units") or {}).get("delta1", "")):
                    for rec in (doc.get("methods") or {}).values():
                        for k in ("delta1", "delta2", "delta3"):
                            if isinstance(rec.get(k), (int, float)):
                                rec[k] = rec[k] / 100.0
                depth.append(doc)
        f = paths.evaluation_root / "depth_finetune.json"      # written by train_depth
        if f.is_file():
            finetune.append(_read(f))
    return depth, finetune


def read_pose_files(output_dir: Path, patients: list[str], sequences: list[str]) -> list[dict]:
    """Per-sequence ``evaluation/pose.json`` docs that exist."""
    docs = []
    for pat in patients:
        for seq in sequences:
            f = PatientPaths(output_dir, pat).evaluation(seq) / "pose.json"
            if f.is_file():
                docs.append(_read(f))
    return docs


def build_tables(pose_docs: list[dict], depth_docs: list[dict], finetune_docs: list[dict], digits: int,
                 pose_order: tuple = ()) -> dict:
    """{table name: Table}."""
    return {"table_1_pose": pose_table(pose_docs, digits, pose_order),
            "table_2_depth": depth_table(depth_docs, digits),
            "table_3_finetune": finetune_table(finetune_docs, digits)}


def write_reports(out: Path, tables: dict, counts: dict) -> None:
    for name, t in tables.items():
        write_text(out / f"{name}.md", t.to_markdown())
        write_text(out / f"{name}.tex", t.to_latex())
        write_text(out / f"{name}.csv", t.to_csv())
    write_text(out / "pose_speed_accuracy.csv", speed_accuracy_csv(tables["table_1_pose"]))
    write_json(out / "metrics.json", _finite(round_floats({
        **{name: t.numbers for name, t in tables.items()}, "inputs": counts,
        "units": {"RRA@5, RTA@5, AUC@30, registration_rate, delta1": "fractions in [0, 1]",
                  "ate_rmse_mm, L1_mm, RMSE_mm": "mm", "seconds_per_frame": "s"},
        "paper": {"source": paper.SOURCE, "retrieved": {k: v["retrieved"] for k, v in paper.TABLES.items()}}}, 6)))


def run(cfg: DictConfig, key: str) -> dict:
    ev = _evaluate_section(cfg)
    p = TablesParams.from_dict(ev.get("tables"))
    patients, sequences = _targets(cfg, key)
    output_dir = Path(cfg.output_dir)
    pose_docs = read_pose_files(output_dir, patients, sequences)
    depth_docs, finetune_docs = read_depth_files(output_dir, patients, sequences)
    order = tuple((ev.get("pose") or {}).get("methods") or ())
    tables = build_tables(pose_docs, depth_docs, finetune_docs, p.digits, order)
    counts = {"patients": len(patients), "sequences": len(patients) * len(sequences),
              "pose_json": len(pose_docs), "depth_json": len(depth_docs), "depth_finetune_json": len(finetune_docs)}
    write_reports(Path(p.output_dir), tables, counts)
    return counts
