"""The registry of monocular depth estimators and the ``depth`` config section.

An estimator turns one RGB frame into a depth map::

    est = create("physics", params, info)      # may raise BackendUnavailable (missing package / weights)
    depth = est.predict(Frame(rgb, camera, index))

``predict`` returns an (H, W) float32 map: planar depth in metres for a
``scaling == "metric"`` estimator, depth in arbitrary units (positive, up to a
scale) for ``"median"`` ones, NaN/<= 0 where it has no answer.  An estimator
with ``resizes = True`` may answer at its own resolution; the evaluator
resizes it to the ground truth's (bilinear) -- any other shape mismatch is an
error (:func:`room_pipeline.depth.metrics.fit_to_shape`).

Names (``depth.methods``)
    ``physics``            inverse-square shading baseline, metric (:mod:`.physics`); an ORACLE: it reads the
                           renderer's light power, albedo and exposure from metadata/render.json
    ``shading_sfs``        weight-free co-located-light shading + shape from shading, image only (:mod:`.baselines`)
    ``constant``, ``train_mean``, ``tube_prior``   image-blind trivial baselines (:mod:`.baselines`)
    ``cnn``                the small U-Net fine-tuned on phantom sequences (:mod:`.cnn`)
    ``cnn_pretrained``     the same network before fine-tuning (Table III's "before")
    any key of ``depth.hf``        a Hugging Face ``transformers`` depth model from a local folder (:mod:`.hf`)
    any key of ``depth.external``  predictions from a folder or a ``module:function`` (:mod:`.external`)

A missing optional dependency (torch, transformers), missing weights or a
missing prediction folder raise :class:`~room_pipeline.errors.BackendUnavailable`
with the reason; the evaluation stage reports the method as unavailable and
goes on.

The interface (:class:`Estimator`, :class:`Frame`, :class:`SequenceInfo`, :class:`Sample`) lives in
:mod:`.base`, which the estimator modules import, so this registry imports them without a cycle.

Also here: :func:`sequence_samples` (the frames of a rendered sequence, loaded
lazily) and :func:`evaluate` (every estimator on every frame, one table row per
method and scaling, with per-frame errors and timings).
"""
from __future__ import annotations

import dataclasses
import json
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..catalog import DEPTH_MODEL, RGB_NOISY, RGB_SOURCES, SequencePaths
from ..config.params import params_from_dict
from ..conventions import MM
from ..errors import BackendUnavailable, ConfigError, InputError
from ..io.images import read_exr, read_png
from ..render.camera import CameraIntrinsics
from .base import SCALINGS, Estimator, Frame, Sample, SequenceInfo  # noqa: F401 (re-exported)
from .baselines import ShadingParams
from .cnn import CNNParams, TrainParams
from .external import ExternalSpec
from .hf import HFModelSpec
from .metrics import MedianScaler, aggregate, fit_to_shape, frame_errors
from .physics import LightModel, PhysicsParams, light_is_coaxial, physics_depth

INPUTS = RGB_SOURCES


# ----------------------------------------------------------------------------- config


@dataclasses.dataclass(frozen=True)
class DepthParams:
    """The ``depth`` config section (conf/depth/default.yaml; units in the key names).

    Build it with :meth:`from_dict`, which also parses the nested sections
    (``physics``, ``cnn``, ``train``) and checks every ``hf`` / ``external`` entry.
    """

    methods: tuple = ("physics", "cnn", "cnn_pretrained")
    also_median: bool = True
    valid_range_mm: tuple = (1.0, 200.0)
    input: str = RGB_NOISY
    frame_stride: int = 3
    max_frames: int | None = None
    physics: PhysicsParams = PhysicsParams()
    cnn: CNNParams | None = None
    train: TrainParams | None = None
    hf: Mapping[str, Any] | None = None
    external: Mapping[str, Any] | None = None
    shading_sfs: ShadingParams | None = None

    @property
    def valid_range_m(self) -> tuple[float, float]:
        return (float(self.valid_range_mm[0]) * MM, float(self.valid_range_mm[1]) * MM)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "DepthParams":
        d = dict(d or {})
        nested = {k: d.pop(k, None) for k in ("physics", "cnn", "train", "hf", "external", "shading_sfs")}
        p = params_from_dict(cls, d, "depth")
        hf = dict(nested["hf"] or {})
        ext = dict(nested["external"] or {})
        p = dataclasses.replace(
            p, physics=params_from_dict(PhysicsParams, nested["physics"], "depth.physics"),
            cnn=params_from_dict(CNNParams, nested["cnn"], "depth.cnn"),
            train=TrainParams.from_dict(nested["train"]), hf=hf, external=ext,
            shading_sfs=params_from_dict(ShadingParams, nested["shading_sfs"], "depth.shading_sfs"))
        lo, hi = (float(x) for x in p.valid_range_mm)
        if not 0 < lo < hi:
            raise ConfigError(f"depth.valid_range_mm must be [lo, hi] with 0 < lo < hi, got {list(p.valid_range_mm)}")
        if p.input not in INPUTS:
            raise ConfigError(f"depth.input must be one of {INPUTS}, got {p.input!r}")
        if p.frame_stride < 1 or (p.max_frames is not None and int(p.max_frames) < 1):
            raise ConfigError("depth: frame_stride >= 1 and max_frames >= 1 (or null) required")
        both = (set(hf) & set(ext)) | ((set(hf) | set(ext)) & set(BUILTIN))
        if both:
            raise ConfigError(f"depth: method name {sorted(both)[0]!r} is defined twice (built-in, hf, external)")
        for name, spec in hf.items():              # validate every entry now: config errors before any work
            HFModelSpec.from_dict(spec, f"depth.hf.{name}")
        for name, spec in ext.items():
            ExternalSpec.from_dict(spec, f"depth.external.{name}")
        unknown = [m for m in p.methods if m not in BUILTIN and m not in hf and m not in ext]
        if unknown:
            raise ConfigError(f"depth.methods: unknown method {unknown[0]!r} (built-in: {', '.join(BUILTIN)}; "
                              f"hf: {', '.join(hf) or 'none'}; external: {', '.join(ext) or 'none'})")
        return p


# ----------------------------------------------------------------------------- built-in estimators


class PhysicsEstimator(Estimator):
    """Inverse-square shading baseline; metric with the sequence's own light model."""

    scaling = "metric"

    def __init__(self, name: str, params: PhysicsParams, model: LightModel) -> None:
        self.name, self.params, self.model = name, params, model

    def predict(self, frame: Frame) -> np.ndarray:
        return physics_depth(frame.rgb, frame.camera, self.model.at_frame(frame.index), self.params)

    def describe(self) -> dict:
        return {"params": dataclasses.asdict(self.params), "exposure_ev": self.model.exposure_ev,
                "exposure": "per frame (render.json film.frame_ev)" if self.model.frame_ev else "fixed",
                "light": dataclasses.asdict(self.model.light), "material": dataclasses.asdict(self.model.material),
                "light_coaxial": light_is_coaxial(self.model)}


def _physics(name: str, params: DepthParams, info: SequenceInfo) -> Estimator:
    if not info.renderer:
        raise BackendUnavailable("physics baseline needs the renderer's light model (metadata/render.json)")
    return PhysicsEstimator(name, params.physics, LightModel.from_render_metadata(info.renderer))


def _cnn(which: str) -> Callable[[str, DepthParams, SequenceInfo], Estimator]:
    def make(name: str, params: DepthParams, info: SequenceInfo) -> Estimator:
        from .cnn import CNNEstimator, checkpoint_path

        if info.output_dir is None:
            raise BackendUnavailable("cnn: no output_dir to find the trained checkpoint in")
        return CNNEstimator.load(name, checkpoint_path(info.output_dir, params.cnn.checkpoint_patient, which),
                                 params.cnn)
    return make


def _baseline(kind: str) -> Callable[[str, DepthParams, SequenceInfo], Estimator]:
    def make(name: str, params: DepthParams, info: SequenceInfo) -> Estimator:
        from . import baselines as bl

        if kind == "constant":
            return bl.ConstantDepth(name)
        if kind == "tube_prior":
            return bl.TubePrior(name)
        if kind == "shading_sfs":
            return bl.ShadingSfS(name, params.shading_sfs or bl.ShadingParams())
        if info.output_dir is None:
            raise BackendUnavailable("train_mean: no output_dir to find the training mean in")
        return bl.TrainMean(name, Path(info.output_dir) / params.cnn.checkpoint_patient / DEPTH_MODEL
                            / bl.TRAIN_MEAN_FILE)
    return make


#: built-in name -> factory(name, params, info)
BUILTIN: dict[str, Callable[[str, DepthParams, SequenceInfo], Estimator]] = {
    "physics": _physics,
    "cnn": _cnn("finetuned"),
    "cnn_pretrained": _cnn("pretrained"),
    "shading_sfs": _baseline("shading_sfs"),
    "constant": _baseline("constant"),
    "train_mean": _baseline("train_mean"),
    "tube_prior": _baseline("tube_prior"),
}
#: rows that read information a real endoscope image does not carry (the renderer's light model)
ORACLES = ("physics",)
#: rows fitted on the training patient (``depth.cnn.checkpoint_patient``): never scored on that patient
TRAINED_ON_CHECKPOINT_PATIENT = ("cnn", "train_mean")


def create(name: str, params: DepthParams, info: SequenceInfo) -> Estimator:
    """The estimator called ``name``; BackendUnavailable (with the reason) when it cannot run here."""
    if name in BUILTIN:
        return BUILTIN[name](name, params, info)
    if params.hf and name in params.hf:
        from .hf import HFDepthEstimator, HFModelSpec

        return HFDepthEstimator(name, HFModelSpec.from_dict(params.hf[name], f"depth.hf.{name}"))
    if params.external and name in params.external:
        from .external import ExternalSpec, create_external

        return create_external(name, ExternalSpec.from_dict(params.external[name], f"depth.external.{name}"), info)
    raise ConfigError(f"unknown depth method {name!r}")


def try_create(name: str, params: DepthParams, info: SequenceInfo) -> tuple[Estimator | None, str | None]:
    """(estimator, None) or (None, reason) when it is unavailable here."""
    try:
        return create(name, params, info), None
    except BackendUnavailable as exc:
        return None, str(exc)


# ----------------------------------------------------------------------------- sequences on disk


def sequence_samples(seq_dir: Path, input_folder: str = "rgb", stride: int = 1, max_frames: int | None = None,
                     group: str | None = None) -> list[Sample]:
    """Every ``stride``-th frame (at most ``max_frames``) of a rendered sequence among those that have both
    ``<input_folder>/frame_NNNN.png`` and ``depth/frame_NNNN.exr``; ``group`` defaults to the folder."""
    seq_dir = Path(seq_dir)
    sp = SequencePaths(seq_dir)
    img_dir, depth_dir, calib = sp.folder(input_folder), sp.folder("depth"), sp.camera
    for p in (img_dir, depth_dir, calib):
        if not p.exists():
            raise InputError(f"{seq_dir}: missing {p.relative_to(seq_dir)} (render the sequence first)")
    cam = CameraIntrinsics.from_dict(json.loads(calib.read_text(encoding="utf-8")))
    names = sorted(p.stem for p in img_dir.glob("frame_*.png") if (depth_dir / f"{p.stem}.exr").is_file())
    if not names:
        raise InputError(f"{seq_dir}: no frame has both {input_folder}/frame_NNNN.png and depth/frame_NNNN.exr")
    indices = list(range(0, len(names), stride))
    if max_frames is not None:
        indices = indices[: int(max_frames)]
    grp = group or str(seq_dir)

    def rgb_loader(n: str) -> Callable[[], np.ndarray]:
        def load() -> np.ndarray:
            a = read_png(img_dir / f"{n}.png")
            if a.ndim != 3 or a.shape[2] < 3 or a.dtype != np.uint8:
                raise InputError(f"{img_dir / n}.png: expected 8-bit RGB, got {a.dtype} {a.shape}")
            return a[..., :3]
        return load

    def gt_loader(n: str) -> Callable[[], np.ndarray]:
        return lambda: read_exr(depth_dir / f"{n}.exr")[0]

    return [Sample(grp, int(names[i].split("_")[-1]), names[i], cam, rgb_loader(names[i]), gt_loader(names[i]))
            for i in indices]


# ----------------------------------------------------------------------------- evaluation loop


@dataclasses.dataclass
class MethodResult:
    """One table row: a method in one scaling, its per-frame errors and timings."""

    name: str
    method: str
    scaling: str
    frames: list = dataclasses.field(default_factory=list)        # FrameErrors, in sample order
    seconds: list = dataclasses.field(default_factory=list)       # predict() wall time per frame
    cpu_seconds: list = dataclasses.field(default_factory=list)   # predict() CPU time of the process per frame
    scales: dict = dataclasses.field(default_factory=dict)        # group -> median scale

    def summary(self) -> dict:
        out = aggregate(self.frames)
        out["seconds_per_frame"] = float(np.mean(self.seconds)) if self.seconds else float("nan")
        out["cpu_seconds_per_frame"] = float(np.mean(self.cpu_seconds)) if self.cpu_seconds else float("nan")
        out["scaling"] = self.scaling
        if self.scales:
            out["median_scale"] = {g: float(s) for g, s in self.scales.items()}
        return out


def evaluate(estimators: Mapping[str, Estimator], samples: list[Sample], valid_range_m: tuple[float, float],
             also_median: bool = True, force_median: bool = False) -> dict[str, MethodResult]:
    """Run every estimator on every sample and compute the errors (see :mod:`.metrics`).

    Each estimator gives one row in its own scaling (``force_median``: median
    for all); a metric estimator also gives ``<name>_median`` when
    ``also_median``.  Median rows use one scale per sample group, so their
    predictions are cached on disk (float32 ``.npy`` in a temporary folder)
    between the pass that collects the medians and the one that scores.
    """
    rows: dict[str, MethodResult] = {}
    median_of: dict[str, str] = {}            # row name -> estimator name
    for name, est in estimators.items():
        if est.scaling not in SCALINGS:
            raise ConfigError(f"estimator {name!r}: scaling must be one of {SCALINGS}, got {est.scaling!r}")
        if est.scaling == "metric" and not force_median:
            rows[name] = MethodResult(name, name, "metric")
            if also_median:
                rows[f"{name}_median"] = MethodResult(f"{name}_median", name, "median")
                median_of[f"{name}_median"] = name
        else:
            rows[name] = MethodResult(name, name, "median")
            median_of[name] = name
    scalers: dict[tuple[str, str], MedianScaler] = {}
    with tempfile.TemporaryDirectory(prefix="room-depth-") as tmp:
        cache = Path(tmp)
        for k, s in enumerate(samples):
            rgb, gt = s.load_rgb(), s.load_gt()
            frame = Frame(rgb, s.camera, s.index)
            for name, est in estimators.items():
                t0, c0 = time.perf_counter(), time.process_time()
                raw = est.predict(frame)
                dt, dc = time.perf_counter() - t0, time.process_time() - c0
                pred = fit_to_shape(raw, gt.shape, est.resizes, where=f"{name} on {s.group}/{s.name}")
                for row in rows.values():
                    if row.method != name:
                        continue
                    row.seconds.append(dt)
                    row.cpu_seconds.append(dc)
                    if row.scaling == "metric":
                        row.frames.append(frame_errors(gt, pred, valid_range_m))
                if any(m == name for m in median_of.values()):
                    scalers.setdefault((name, s.group), MedianScaler(valid_range_m)).add(gt, pred)
                    np.save(cache / f"{name}_{k}.npy", np.asarray(raw, dtype=np.float32))
        if median_of:
            scale_of = {key: sc.scale() for key, sc in scalers.items()}     # once per (method, group)
            for k, s in enumerate(samples):
                gt = s.load_gt()
                for row_name, name in median_of.items():
                    est = estimators[name]
                    pred = fit_to_shape(np.load(cache / f"{name}_{k}.npy"), gt.shape, est.resizes)
                    scale = scale_of[(name, s.group)]
                    rows[row_name].scales[s.group] = scale
                    rows[row_name].frames.append(frame_errors(gt, pred, valid_range_m, scale=scale if np.isfinite(scale)
                                                              else float("nan")))
    return rows
