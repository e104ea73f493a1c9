"""Monocular depth benchmark: accuracy and speed of every estimator and the fine-tuning experiment.

    .venv/bin/python benchmarks/depth_eval.py --data DIR [--other-patient ID] [--quick]

DIR is a COPY of a rendered default run (``cp -al data/output /scratch/output``: the stages run here write
their outputs into it): ``DIR/patient_000/sequence_000`` (the default phantom, the training patient) and, for
the other-anatomy rows, ``DIR/<other patient>/sequence_000`` (default: ``patient_001``, the default run's
second phantom seed, else ``medmpd_1`` when present: a patient built from a shared real airway mask, e.g.
``room run --patient medmpd_1 patients=shared_masks output_dir=DIR 'sequences=[sequence_000]'``).
Frames are read as the stages read them (``depth.input``: the noisy RGB by default).

Writes benchmarks/results/depth_eval.{json,md}:
  1. physics baseline: how to treat the unknown cosine (unit, iterated 1-3 times, the cosine of the
     ground-truth depth as an upper bound), metric and median-scaled, on every ``depth.frame_stride``-th
     frame of the whole sequence (``--quick``: every 5th of those);
  2. the train_depth stage with the default config (+ the other patient as other anatomy): time,
     before / after on every dataset (Table III);
  3. the evaluate_depth stage at the default protocol (whole sequence, every ``depth.frame_stride``-th frame)
     on the training sequence and on the other-anatomy sequence: each method's accuracy next to its seconds
     per frame (Table II), and the stage's wall and CPU time; without ``--quick`` also the training sequence at
     every frame (against the stride: what the stride costs in accuracy) and the Hugging Face architectures'
     speed with random weights.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from omegaconf import OmegaConf  # noqa: E402

from room_pipeline.catalog import SequencePaths  # noqa: E402
from room_pipeline.depth import metrics as dm  # noqa: E402
from room_pipeline.depth.estimators import DepthParams, sequence_samples  # noqa: E402
from room_pipeline.depth.physics import (LightModel, PhysicsParams, _log_distance, _rays, brdf_k,  # noqa: E402
                                         camera_cos, physics_depth, srgb8_to_linear)
from room_pipeline.paths import PatientPaths  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


def config(data: Path, others: list[str], **depth) -> OmegaConf:
    base = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "depth" / "default.yaml"))
    for k, v in depth.items():
        if isinstance(v, dict):
            base[k] = {**base.get(k, {}), **v}
        else:
            base[k] = v
    patients = {"patient_000": {"kind": "ct", "input": str(PatientPaths(data, "patient_000").phantom_ct)}}
    phantoms = {"patient_000": {"seed": 0}}
    for q in others:
        if q.startswith("patient_"):        # a phantom seed of the default run
            patients[q] = {"kind": "ct", "input": str(PatientPaths(data, q).phantom_ct)}
            phantoms[q] = {"seed": int(q.split("_")[-1])}
        else:
            patients[q] = {"kind": "mask", "input": "../shared/data/airway_masks"}
    return OmegaConf.create({"output_dir": str(data), "sequences": ["sequence_000"],
                             "phantoms": phantoms, "patients": patients, "depth": base})


def physics_variants(seq: Path, stride: int, folder: str) -> list[dict]:
    samples = sequence_samples(seq, folder, stride=stride)
    meta = json.loads(SequencePaths(seq).render_json.read_text())["renderer"]
    model = LightModel.from_render_metadata(meta)
    cam = samples[0].camera
    frames = [(s.load_rgb(), s.load_gt()) for s in samples]
    rng = DepthParams.from_dict({}).valid_range_m
    variants = [("unit cosine", PhysicsParams(cos_model="unit")),
                ("iterate x1, blur 1 px", PhysicsParams(iterations=1, normal_smoothing_px=1.0)),
                ("iterate x1, blur 2 px (default)", PhysicsParams(iterations=1, normal_smoothing_px=2.0)),
                ("iterate x1, blur 4 px", PhysicsParams(iterations=1, normal_smoothing_px=4.0)),
                ("iterate x2, blur 2 px", PhysicsParams(iterations=2, normal_smoothing_px=2.0)),
                ("iterate x3, blur 2 px", PhysicsParams(iterations=3, normal_smoothing_px=2.0)),
                ("cosine of the ground-truth depth (upper bound)", None)]
    rows = []
    for label, prm in variants:
        preds, t = [], 0.0
        for rgb, gt in frames:
            t0 = time.perf_counter()
            if prm is None:                      # not an estimator: uses the ground truth's normals
                lin = srgb8_to_linear(rgb) * np.float32(2.0 ** -model.exposure_ev)
                cos = np.clip(camera_cos(np.where(gt > 0, gt, 1.0), cam, 1.0), 0.05, 1.0)
                p = np.exp(_log_distance(lin, rgb, brdf_k(cos, model), 255)) / _rays(cam)[2]
            else:
                p = physics_depth(rgb, cam, model, prm)
            t += time.perf_counter() - t0
            preds.append(p)
        gts = [g for _, g in frames]
        metric = dm.aggregate([dm.frame_errors(g, p, rng) for g, p in zip(gts, preds)])
        s = dm.median_scale(gts, preds, rng)
        med = dm.aggregate([dm.frame_errors(g, p, rng, s) for g, p in zip(gts, preds)])
        rows.append({"variant": label, "sequence": f"{seq.parent.name}/{seq.name}", "stride": stride,
                     "metric": {k: metric[k] for k in dm.METRIC_KEYS},
                     "median": {k: med[k] for k in dm.METRIC_KEYS}, "median_scale": s,
                     "seconds_per_frame": t / len(frames), "frames": len(frames)})
        print(f"physics {label}: metric AbsRel {metric['AbsRel']:.4f}, median AbsRel {med['AbsRel']:.4f}, "
              f"{t / len(frames):.3f} s/frame", flush=True)
    return rows


def hf_architecture_speed(seq: Path, tmp: Path, n: int = 3) -> list[dict]:
    """Seconds per 600x600 frame of the real Depth Anything V2 Small and DPT (ViT-B/16, 384) architectures with
    random weights (speed only: no weights can be downloaded here, so no accuracy), through the same adapter."""
    import torch
    import transformers as tr

    from room_pipeline.depth.estimators import Frame
    from room_pipeline.depth.hf import HFDepthEstimator, HFModelSpec

    torch.manual_seed(0)
    models = {
        "Depth Anything V2 Small architecture (ViT-S/14, 518 px)": (
            tr.DepthAnythingForDepthEstimation(tr.DepthAnythingConfig()),
            tr.DPTImageProcessor(size={"height": 518, "width": 518}, keep_aspect_ratio=True, ensure_multiple_of=14,
                                 do_pad=False)),
        "DPT architecture (ViT-B/16, 384 px)": (
            tr.DPTForDepthEstimation(tr.DPTConfig()), tr.DPTImageProcessor(size={"height": 384, "width": 384})),
    }
    samples = sequence_samples(seq, max_frames=n)
    rows = []
    for label, (model, proc) in models.items():
        d = tmp / label.split()[0]
        model.save_pretrained(d)
        proc.save_pretrained(d)
        for threads in (1, 2):
            est = HFDepthEstimator(label, HFModelSpec(path=str(d), threads=threads))
            frame = Frame(samples[0].load_rgb(), samples[0].camera)
            est.predict(frame)                                       # warm-up
            t0 = time.perf_counter()
            for s in samples:
                est.predict(Frame(s.load_rgb(), s.camera))
            dt = (time.perf_counter() - t0) / len(samples)
            rows.append({"architecture": label, "threads": threads, "n_parameters": est.describe()["n_parameters"],
                         "seconds_per_frame": dt, "frames_timed": len(samples), "seconds_per_100_frames": 100 * dt})
            print(f"{label}, {threads} thread(s): {dt:.2f} s/frame", flush=True)
    return rows


def saturation_blocks(seq: Path, errors_csv: Path, folder: str, block: int = 50) -> list[dict]:
    """Per block of frames: the fraction of pixels clipped (code 255) in every channel, and the per-frame AbsRel
    of the evaluate_depth rows from its depth_errors.csv (run at frame_stride 1 on the whole sequence)."""
    import csv

    with open(errors_csv) as fh:
        rows = list(csv.DictReader(fh))
    samples = sequence_samples(seq, folder)
    clipped = np.array([float((s.load_rgb() == 255).all(axis=-1).mean()) for s in samples])
    cols = [c for c in rows[0] if c.endswith("_AbsRel")]
    out = []
    for i in range(0, len(samples), block):
        rec = {"frames": f"{samples[i].name}..{samples[min(i + block, len(samples)) - 1].name}",
               "clipped_fraction": float(clipped[i:i + block].mean())}
        for c in cols:
            v = [float(r[c]) for r in rows[i:i + block] if r[c]]
            rec[c] = float(np.mean(v)) if v else None
        out.append(rec)
    return out


def run_eval(cfg, key: str) -> dict:
    from room_pipeline.stages import evaluate_depth

    t0, c0 = time.perf_counter(), time.process_time()
    evaluate_depth.run(cfg, key)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    from room_pipeline.io.metrics import read_with_timings

    patient, seq = key.split("/")
    paths = PatientPaths(Path(cfg.output_dir), patient)
    # depth.json holds no timing: the rows' seconds per frame are in the stage's timing file
    doc = read_with_timings(paths.eval(seq).depth, paths.stage_timings("evaluate_depth", seq))
    print(f"evaluate_depth {key}: {doc['n_frames']} frames in {wall:.1f} s ({cpu:.1f} CPU s)", flush=True)
    return {"key": key, "frames": doc["n_frames"], "stride": int(cfg.depth.frame_stride), "wall_s": wall,
            "cpu_s": cpu, "methods": doc["methods"], "errors_csv": str(paths.eval(seq).depth_errors)}


def fmt(x, nd=3) -> str:
    return "n/a" if x is None else f"{x:.{nd}f}"


def markdown(res: dict) -> str:
    L = ["# Monocular depth benchmark (benchmarks/depth_eval.py)", "",
         f"`{res['command']}` on {res['machine']}; load average {res['load_start']} at start, "
         f"{res['load_end']} at end (2 cores shared with other work: timings are noisy).", "",
         f"Data: {res['data_note']}", "",
         "Metrics: frame-averaged over pixels with ground truth in [1, 200] mm; 'median' = one scale per "
         "sequence, median(gt)/median(pred). L1 and RMSE in mm.", ""]
    L += ["## 1. Physics baseline (ORACLE: reads the renderer's light model): the unknown cosine", "",
          "Whole sequences, every n-th frame (frames column), 600x600, input as depth.input.", "",
          "| sequence | frames | variant | metric AbsRel | metric delta1 | metric L1 | median AbsRel | median delta1 | "
          "median L1 | median scale | s/frame |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["physics"]:
        m, d = r["metric"], r["median"]
        L.append(f"| {r['sequence']} | {r['frames']} | {r['variant']} | {m['AbsRel']:.4f} | {m['delta1']:.3f} | "
                 f"{m['L1_mm']:.2f} | {d['AbsRel']:.4f} | "
                 f"{d['delta1']:.3f} | {d['L1_mm']:.2f} | {r['median_scale']:.3f} | {r['seconds_per_frame']:.3f} |")
    tr = res["train"]
    t, tt = tr["training"], tr["training"]["times_s"]
    L += ["", "## 2. Fine-tuning experiment (stage train_depth, default config) -- Table III", "",
          f"Wall time {tr['wall_s']:.0f} s (synthetic data {tt['synthetic_data']:.0f} s, pretraining "
          f"{tt['pretrain']:.0f} s, fine-tuning data {tt['finetune_data']:.0f} s, fine-tuning {tt['finetune']:.0f} s, "
          f"evaluation {tt['evaluation']:.0f} s; CPU time {tt['cpu_total']:.0f} s); {t['n_parameters']} parameters, "
          f"torch threads: {t['threads']}; pretraining on {t['pretrain']['frames']} synthetic frames, fine-tuning on "
          f"{t['finetune']['frames']} phantom frames.", "",
          f"before = {tr['training']['definition']['before']}; after = {tr['training']['definition']['after']}.", "",
          "| dataset | frames | before AbsRel | after AbsRel | before delta1 | after delta1 | before L1 | after L1 | "
          "source |", "|---|---|---|---|---|---|---|---|---|"]
    for name, d in tr["datasets"].items():
        if not d["available"]:
            L.append(f"| {name} | 0 | n/a | n/a | n/a | n/a | n/a | n/a | unavailable: {d['reason']} |")
            continue
        b, a = d["before"], d["after"]
        L.append(f"| {name} | {d['n_frames']} | {b['AbsRel']:.4f} | {a['AbsRel']:.4f} | {b['delta1']:.3f} | "
                 f"{a['delta1']:.3f} | {b['L1_mm']:.2f} | {a['L1_mm']:.2f} | {d['source']} |")
    L += ["", "Loss (scale-invariant log error), mean per block of 25 steps:", ""]
    for ph, curve in res["loss_curve"].items():
        L.append(f"- {ph}: " + ", ".join(f"{v:.3f}" for v in curve))
    L += ["", "## 3. Speed against error (stage evaluate_depth) -- Table II", ""]
    for ev in res["evaluations"]:
        L += [f"### {ev['key']}: {ev['frames']} frames (the whole sequence, frame_stride {ev['stride']}), stage wall "
              f"time {ev['wall_s']:.1f} s, CPU {ev['cpu_s']:.1f} s", "",
              "| method | scaling | AbsRel | delta1 | L1 (mm) | RMSE (mm) | s/frame | CPU s/frame | note |",
              "|---|---|---|---|---|---|---|---|---|"]
        for name, m in ev["methods"].items():
            if m["available"]:
                L.append(f"| {name} | {m['scaling']} | {fmt(m['AbsRel'], 4)} | {fmt(m['delta1'])} | "
                         f"{fmt(m['L1_mm'], 2)} | {fmt(m['RMSE_mm'], 2)} | {fmt(m['seconds_per_frame'])} | "
                         f"{fmt(m['cpu_seconds_per_frame'])} | {m.get('note', '')} |")
            else:
                L.append(f"| {name} | {m['scaling']} | n/a | n/a | n/a | n/a | n/a | n/a | "
                         f"unavailable: {m['reason']} |")
        L.append("")
    L += ["### Hugging Face architectures with random weights (speed only, through the adapter)", "",
          "No pretrained weights can be downloaded here, so these rows give the cost of the real architectures, "
          "not their accuracy (not measured with --quick).", "",
          "| architecture | parameters | torch threads | s/frame (600x600 input) | "
          "s per 100 frames |", "|---|---|---|---|---|"]
    for r in res.get("hf_speed") or []:
        L.append(f"| {r['architecture']} | {r['n_parameters']} | {r['threads']} | {r['seconds_per_frame']:.2f} | "
                 f"{r['seconds_per_100_frames']:.0f} |")
    L.append("")
    if res.get("saturation"):
        sat = res["saturation"]
        cols = [c for c in sat[0] if c.endswith("_AbsRel")]
        L += ["### Along the route: clipping and error per block of frames", "",
              "Fraction of pixels clipped in all three channels and the mean per-frame AbsRel of each row (median "
              "rows use the whole sequence's single scale), per block of patient_000/sequence_000 (every frame):", "",
              "| frames | clipped | " + " | ".join(c[:-len("_AbsRel")] for c in cols) + " |",
              "|---|---|" + "---|" * len(cols)]
        for r in sat:
            L.append(f"| {r['frames']} | {r['clipped_fraction']:.3f} | " + " | ".join(fmt(r[c]) for c in cols) + " |")
        L.append("")
    return "\n".join(L) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="folder with rendered sequences (see the docstring)")
    ap.add_argument("--other-patient", "--mask-patient", dest="other",
                    help="other-anatomy patient in DATA (default: patient_001, else medmpd_1, when rendered)")
    ap.add_argument("--quick", action="store_true", help="default protocol only, physics variants on every 5th "
                                                         "evaluated frame, no Hugging Face speed rows")
    args = ap.parse_args()
    data = args.data.resolve()
    seq = data / "patient_000" / "sequence_000"
    conf = DepthParams.from_dict(OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "depth" / "default.yaml")))
    folder = conf.input
    if not (seq / "rgb").is_dir():
        print(f"no rendered sequence at {seq}: see the docstring for how to make it", file=sys.stderr)
        return 2
    if not (seq / folder).is_dir():
        folder = "rgb"
    candidates = [args.other] if args.other else ["patient_001", "medmpd_1"]
    masks = [q for q in candidates if (data / q / "sequence_000" / "rgb").is_dir()][:1]
    stride = int(conf.frame_stride)
    n_frames = len(list((seq / "rgb").glob("*.png")))
    res = {"command": "python benchmarks/depth_eval.py " + " ".join(sys.argv[1:]),
           "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores", "load_start": os.getloadavg()[0],
           "data_note": f"{data}: patient_000/sequence_000 ({n_frames} frames, 600x600, input {folder}/)"
                        + (f"; {masks[0]}/sequence_000 "
                           f"({len(list((data / masks[0] / 'sequence_000' / 'rgb').glob('*.png')))} frames)"
                           if masks else "; no other patient")}
    import torch
    import transformers

    res["versions"] = {"torch": str(torch.__version__), "transformers": transformers.__version__,
                       "numpy": np.__version__}
    pstride = stride * (5 if args.quick else 1)
    res["physics"] = physics_variants(seq, pstride, folder)
    if masks:
        res["physics"] += physics_variants(data / masks[0] / "sequence_000", pstride, folder)
    import tempfile

    if not args.quick:
        with tempfile.TemporaryDirectory() as tmp:
            res["hf_speed"] = hf_architecture_speed(seq, Path(tmp))

    from room_pipeline.io.metrics import read_metrics_file
    from room_pipeline.stages import train_depth

    cfg = config(data, masks)
    t0 = time.perf_counter()
    train_depth.run(cfg, "patient_000")
    wall = time.perf_counter() - t0
    doc = read_metrics_file(PatientPaths(data, "patient_000").stage_metrics("train_depth"))   # + times_s
    res["train"] = {"wall_s": wall, **doc}
    import csv

    with open(PatientPaths(data, "patient_000").depth_training_log) as fh:
        log = list(csv.DictReader(fh))
    res["loss_curve"] = {ph: [float(np.mean([float(r["loss"]) for r in log if r["phase"] == ph][i:i + 25]))
                              for i in range(0, sum(r["phase"] == ph for r in log), 25)]
                         for ph in ("pretrain", "finetune")}
    print(f"train_depth: {wall:.0f} s", flush=True)

    evals = [run_eval(config(data, masks), "patient_000/sequence_000")]
    if masks:
        evals.append(run_eval(config(data, masks), f"{masks[0]}/sequence_000"))
    if not args.quick:
        evals.append(run_eval(config(data, masks, frame_stride=1), "patient_000/sequence_000"))
        res["saturation"] = saturation_blocks(seq, Path(evals[-1]["errors_csv"]), folder)
    res["evaluations"] = evals
    res["load_end"] = os.getloadavg()[0]
    RESULTS.mkdir(parents=True, exist_ok=True)
    from room_pipeline.stages.common import _finite

    (RESULTS / "depth_eval.json").write_text(json.dumps(_finite(res), indent=2, sort_keys=True, default=str) + "\n")
    md = markdown(res)
    (RESULTS / "depth_eval.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
