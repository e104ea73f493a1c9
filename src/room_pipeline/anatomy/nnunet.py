"""Inference of a trained nnU-Net v2 model from its local results folder (TotalSegmentator's weights).

TotalSegmentator ships nnU-Net v2 models; its ``lung_vessels`` task is the folder
``<home>/nnunet/results/Dataset258_lung_vessels_248subj/nnUNetTrainer__nnUNetPlans__3d_fullres/`` holding
``plans.json``, ``dataset.json`` and ``fold_0/checkpoint_final.pth``.  This module reads that layout
directly and runs the model with torch, without the nnunetv2 / TotalSegmentator packages (which pull
their own torch and a dozen other packages):

* **network**: ``plans.json`` -> ``configurations.<cfg>.architecture`` (nnU-Net >= 2.4:
  ``network_class_name`` + ``arch_kwargs``, the torch classes named in ``_kw_requires_import``), or the
  older keys (``UNet_class_name``, ``UNet_base_num_features``, ``n_conv_per_stage_encoder`` ...), which
  nnU-Net itself converts the same way; only classes of ``dynamic_network_architectures`` (e.g.
  ``PlainConvUNet``) and of ``torch.nn`` are accepted.  Input channels = ``dataset.json`` ``channel_names``,
  outputs = its ``labels``; the checkpoint's ``network_weights`` are loaded strictly;
* **preprocessing** as nnU-Net's ``DefaultPreprocessor``: the array in the reader's axis order
  (``image_reader_writer``: SimpleITKIO gives (z, y, x) of the RAS-canonical image as TotalSegmentator
  writes it, the nibabel readers (x, y, z)), ``transpose_forward``, crop to the non-zero bounding box,
  ``CTNormalization`` (clip to the foreground's 0.5 / 99.5 percentiles, minus mean, over std) or
  ``ZScoreNormalization``, resampling to the configuration's spacing (cubic; nearest along an axis
  whose spacing is > 3x the others', as nnU-Net's ``order_z``);
* **sliding window** of ``patch_size`` with step ``tile_step_size`` x patch, Gaussian importance
  weighting (sigma = patch / 8), the image zero-padded to at least one patch; no mirroring (as
  TotalSegmentator runs it);
* **export**: logits resampled back (linear) to the cropped shape, argmax, put back into the full
  volume (background outside the crop), axes restored.

Not reproduced: TotalSegmentator's crop to the lungs by its ``total`` model before this one (the whole
scan is segmented: slower, same model) and its postprocessing.  Tested with a tiny randomly initialised
``PlainConvUNet`` saved in this layout (``tests/test_segment.py``), so no weights are needed there.
"""
from __future__ import annotations

import importlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage as ndi

from ..errors import BackendUnavailable

#: modules whose classes a plans file may name (the network and its torch building blocks)
_ALLOWED_MODULES = ("dynamic_network_architectures.", "torch.nn.")


def _locate(name: str):
    if name is None:
        return None
    if not any(name.startswith(m) for m in _ALLOWED_MODULES):
        raise BackendUnavailable(f"nnU-Net plans name the class {name!r}: only dynamic_network_architectures "
                                 "and torch.nn classes are loaded")
    mod, _, cls = name.rpartition(".")
    try:
        return getattr(importlib.import_module(mod), cls)
    except (ImportError, AttributeError) as exc:
        raise BackendUnavailable(f"nnU-Net plans name {name!r}, which cannot be imported: {exc}") from None


def _architecture(cfg: dict) -> tuple[str, dict, tuple]:
    """(class name, kwargs, kwargs to import) of a configuration, old or new plans format."""
    if "architecture" in cfg:
        a = cfg["architecture"]
        return a["network_class_name"], dict(a["arch_kwargs"]), tuple(a.get("_kw_requires_import", ()))
    # nnU-Net < 2.4 plans (TotalSegmentator's weights): the conversion nnU-Net applies when it loads them
    name = cfg["UNet_class_name"]
    cls = {"PlainConvUNet": "dynamic_network_architectures.architectures.unet.PlainConvUNet",
           "ResidualEncoderUNet": "dynamic_network_architectures.architectures.unet.ResidualEncoderUNet"}.get(name)
    if cls is None:
        raise BackendUnavailable(f"nnU-Net plans: unknown UNet_class_name {name!r}")
    n = len(cfg["n_conv_per_stage_encoder"])
    dim = len(cfg["patch_size"])
    conv = "torch.nn.modules.conv.Conv3d" if dim == 3 else "torch.nn.modules.conv.Conv2d"
    norm = ("torch.nn.modules.instancenorm.InstanceNorm3d" if dim == 3
            else "torch.nn.modules.instancenorm.InstanceNorm2d")
    key = "n_conv_per_stage" if name == "PlainConvUNet" else "n_blocks_per_stage"
    kw = {"n_stages": n,
          "features_per_stage": [min(cfg["UNet_base_num_features"] * 2 ** i, cfg["unet_max_num_features"])
                                 for i in range(n)],
          "conv_op": conv, "kernel_sizes": cfg["conv_kernel_sizes"], "strides": cfg["pool_op_kernel_sizes"],
          key: cfg["n_conv_per_stage_encoder"], "n_conv_per_stage_decoder": cfg["n_conv_per_stage_decoder"],
          "conv_bias": True, "norm_op": norm, "norm_op_kwargs": {"eps": 1e-05, "affine": True},
          "dropout_op": None, "dropout_op_kwargs": None,
          "nonlin": "torch.nn.LeakyReLU", "nonlin_kwargs": {"inplace": True}}
    return cls, kw, ("conv_op", "norm_op", "dropout_op", "nonlin")


@dataclass
class NnUNetModel:
    """A loaded nnU-Net v2 model: network (eval mode), plans configuration, labels and intensity statistics."""

    folder: Path
    network: Any
    configuration: dict
    plans: dict
    labels: dict[str, int]
    reader: str

    def label(self, name: str) -> int:
        if name not in self.labels:
            raise BackendUnavailable(f"{self.folder}: dataset.json has no label {name!r} (labels: "
                                     f"{', '.join(self.labels)})")
        return int(self.labels[name])


def find_model_folder(dataset_dir: Path, configuration: str = "3d_fullres") -> Path:
    """The one ``<trainer>__<plans>__<configuration>`` folder of a dataset results folder."""
    cands = sorted(p for p in Path(dataset_dir).glob(f"*__*__{configuration}") if p.is_dir())
    if not cands:
        raise BackendUnavailable(f"{dataset_dir}: no nnU-Net model folder '<trainer>__<plans>__{configuration}' "
                                 "(expected e.g. nnUNetTrainer__nnUNetPlans__3d_fullres with plans.json, "
                                 "dataset.json and fold_0/checkpoint_final.pth)")
    return cands[0]


def load_model(folder: Path, configuration: str = "3d_fullres", fold: int | str = 0,
               checkpoint: str = "checkpoint_final.pth", device: str = "cpu") -> NnUNetModel:
    """Build the plans' network and load ``fold_<fold>/<checkpoint>``; :class:`BackendUnavailable` says what is missing."""
    try:
        import torch
    except ImportError:
        raise BackendUnavailable("nnU-Net inference needs torch (pip install 'room-pipeline[ml]')") from None
    folder = Path(folder)
    files = {n: folder / n for n in ("plans.json", "dataset.json")}
    files["checkpoint"] = folder / f"fold_{fold}" / checkpoint
    for what, p in files.items():
        if not p.is_file():
            raise BackendUnavailable(f"nnU-Net model folder {folder}: {p.name} missing ({p})")
    try:
        plans = json.loads(files["plans.json"].read_text())
        dataset = json.loads(files["dataset.json"].read_text())
        cfg = plans["configurations"][configuration]
        while "inherits_from" in cfg and "patch_size" not in cfg:  # e.g. 3d_cascade_fullres
            cfg = {**plans["configurations"][cfg["inherits_from"]], **cfg}
        cls_name, kwargs, req = _architecture(cfg)
        labels = {str(k): int(v) for k, v in dataset["labels"].items()}
        n_in = len(dataset.get("channel_names", dataset.get("modality", {"0": "CT"})))
    except (KeyError, TypeError, ValueError) as exc:
        raise BackendUnavailable(f"nnU-Net model folder {folder}: unreadable plans/dataset json "
                                 f"({type(exc).__name__}: {exc})") from None
    try:
        importlib.import_module("dynamic_network_architectures")
    except ImportError:
        raise BackendUnavailable("nnU-Net inference needs the package dynamic-network-architectures "
                                 "(pip install 'room-pipeline[totalseg]')") from None
    for k in req:
        if kwargs.get(k) is not None:
            kwargs[k] = _locate(kwargs[k])
    net_cls = _locate(cls_name)
    try:
        net = net_cls(input_channels=n_in, num_classes=len(labels), deep_supervision=False, **kwargs)
    except TypeError as exc:
        raise BackendUnavailable(f"nnU-Net plans of {folder}: cannot build {cls_name}: {exc}") from None
    try:
        ck = torch.load(files["checkpoint"], map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001  a real nnU-Net checkpoint pickles numpy logs: the user's own local file
        ck = torch.load(files["checkpoint"], map_location="cpu", weights_only=False)
    state = ck.get("network_weights", ck) if isinstance(ck, dict) else ck
    state = {k[len("module."):] if k.startswith("module.") else k: v for k, v in state.items()}
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[0]
        raise BackendUnavailable(f"{files['checkpoint']}: weights do not fit the plans' network: {first}") from None
    dev = "cuda" if str(device).startswith("gpu") else "cpu"
    if dev == "cuda":
        idx = str(device).partition(":")[2]
        dev = f"cuda:{idx}" if idx else "cuda"
    try:
        net = net.to(dev).eval()
    except (RuntimeError, AssertionError) as exc:  # no CUDA build / device
        raise BackendUnavailable(f"device {device!r} unavailable for the nnU-Net model: "
                                 f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    return NnUNetModel(folder, net, cfg, plans, labels, str(plans.get("image_reader_writer", "SimpleITKIO")))


# ------------------------------------------------------------------ preprocessing and the sliding window
def _normalize(x: np.ndarray, scheme: str, props: dict | None) -> np.ndarray:
    x = x.astype(np.float32, copy=True)
    if scheme == "CTNormalization":
        if not props:
            raise BackendUnavailable("nnU-Net plans: CTNormalization without foreground intensity properties")
        np.clip(x, props["percentile_00_5"], props["percentile_99_5"], out=x)
        x -= props["mean"]
        x /= max(float(props["std"]), 1e-8)
    elif scheme == "ZScoreNormalization":
        x -= x.mean()
        x /= max(float(x.std()), 1e-8)
    elif scheme not in ("NoNormalization",):
        raise BackendUnavailable(f"nnU-Net plans: normalization scheme {scheme!r} is not supported here")
    return x


def _resample(x: np.ndarray, shape: tuple[int, ...], spacing: np.ndarray, order: int) -> np.ndarray:
    if tuple(x.shape) == tuple(shape):
        return x
    zoom = np.array(shape, float) / np.array(x.shape, float)
    aniso = spacing.max() / spacing.min() > 3.0
    if aniso and order > 0:  # nnU-Net: in-plane at order, the out-of-plane axis nearest
        z = int(np.argmax(spacing))
        inplane = np.ones(3)
        inplane[np.arange(3) != z] = zoom[np.arange(3) != z]
        y = ndi.zoom(x, inplane, order=order, mode="nearest", grid_mode=False)
        zz = np.ones(3)
        zz[z] = zoom[z]
        y = ndi.zoom(y, zz, order=0, mode="nearest", grid_mode=False)
    else:
        y = ndi.zoom(x, zoom, order=order, mode="nearest", grid_mode=False)
    if tuple(y.shape) != tuple(shape):  # zoom rounds; pad/crop the last voxel
        out = np.zeros(shape, y.dtype)
        sl = tuple(slice(0, min(a, b)) for a, b in zip(shape, y.shape))
        out[sl] = y[sl]
        y = out
    return y


def gaussian_importance(patch: tuple[int, ...], sigma_scale: float = 1.0 / 8) -> np.ndarray:
    """nnU-Net's patch weighting: a Gaussian (sigma = patch x scale) peaking at 1, no zero weight."""
    g = np.zeros(patch, np.float32)
    g[tuple(p // 2 for p in patch)] = 1.0
    g = ndi.gaussian_filter(g, [p * sigma_scale for p in patch], order=0, mode="constant", cval=0.0)
    g /= g.max()
    g[g == 0] = g[g > 0].min()
    return g


def window_starts(size: int, patch: int, step: float) -> list[int]:
    """Start offsets of the sliding window along one axis (nnU-Net's ``compute_steps_for_sliding_window``)."""
    n = int(math.ceil((size - patch) / (patch * step))) + 1
    if n <= 1:
        return [0]
    actual = (size - patch) / (n - 1)
    return [int(round(actual * i)) for i in range(n)]


def sliding_window_logits(model: NnUNetModel, x: np.ndarray, step: float = 0.5) -> np.ndarray:
    """(C, *shape) logits of the preprocessed (1-channel) volume ``x`` by Gaussian-weighted tiles."""
    import torch

    patch = tuple(int(p) for p in model.configuration["patch_size"])
    pad = [max(p - s, 0) for p, s in zip(patch, x.shape)]
    lo = [d // 2 for d in pad]
    xp = np.pad(x, [(a, d - a) for a, d in zip(lo, pad)], mode="constant")
    n_cls = len(model.labels)
    acc = np.zeros((n_cls, *xp.shape), np.float32)
    wsum = np.zeros(xp.shape, np.float32)
    g = gaussian_importance(patch)
    dev = next(model.network.parameters()).device
    starts = [window_starts(s, p, step) for s, p in zip(xp.shape, patch)]
    with torch.inference_mode():
        for a in starts[0]:
            for b in starts[1]:
                for c in starts[2]:
                    sl = (slice(a, a + patch[0]), slice(b, b + patch[1]), slice(c, c + patch[2]))
                    t = torch.from_numpy(np.ascontiguousarray(xp[sl]))[None, None].to(dev)
                    out = model.network(t)
                    out = out[0] if isinstance(out, (list, tuple)) else out
                    acc[(slice(None), *sl)] += out[0].float().cpu().numpy() * g
                    wsum[sl] += g
    acc /= wsum[None]
    return acc[(slice(None), *(slice(a, a + s) for a, s in zip(lo, x.shape)))]


def predict(model: NnUNetModel, data: np.ndarray, spacing_mm, step: float = 0.5) -> np.ndarray:
    """Label map (same shape as ``data``) of a single-channel volume given in the reader's axis order.

    ``spacing_mm``: voxel size along ``data``'s axes, mm (nnU-Net's plans are in mm).
    """
    cfg, plans = model.configuration, model.plans
    tf = [int(v) for v in plans.get("transpose_forward", [0, 1, 2])]
    tb = [int(v) for v in plans.get("transpose_backward", list(np.argsort(tf)))]
    x = np.transpose(np.asarray(data), tf)
    sp = np.asarray(spacing_mm, float)[tf]
    nz = x != 0
    if not nz.any():
        return np.zeros(data.shape, np.uint8)
    nz = ndi.binary_fill_holes(nz)
    box = tuple(slice(int(np.flatnonzero(nz.any(axis=tuple(b for b in range(3) if b != a)))[0]),
                      int(np.flatnonzero(nz.any(axis=tuple(b for b in range(3) if b != a)))[-1]) + 1)
                for a in range(3))
    xc = x[box]
    schemes = cfg.get("normalization_schemes", ["CTNormalization"])
    props = (plans.get("foreground_intensity_properties_per_channel") or
             plans.get("foreground_intensity_properties_by_modality") or {}).get("0")
    xn = _normalize(xc, schemes[0], props)
    target = np.asarray(cfg["spacing"], float)
    new_shape = tuple(int(round(s * a / b)) for s, a, b in zip(xc.shape, sp, target))
    xr = _resample(xn, new_shape, sp, order=3)
    logits = sliding_window_logits(model, xr, step)
    back = np.stack([_resample(l, xc.shape, target, order=1) for l in logits])
    lab = np.zeros(x.shape, np.uint8)
    lab[box] = np.argmax(back, axis=0).astype(np.uint8)
    return np.ascontiguousarray(np.transpose(lab, tb))


def predict_volume(model: NnUNetModel, data: np.ndarray, affine_mm: np.ndarray, step: float = 0.5) -> np.ndarray:
    """Label map of a CT on our grid (``affine_mm``: voxel -> RAS+ mm), read as nnU-Net's reader would.

    As TotalSegmentator does, the image is first brought to the closest RAS-canonical axis order; the
    SimpleITK reader then sees (z, y, x), the nibabel readers (x, y, z).
    """
    from nibabel import orientations as ornt

    o = ornt.io_orientation(affine_mm)
    can = ornt.apply_orientation(np.asarray(data), o)
    sp = np.linalg.norm(affine_mm[:3, :3], axis=0)[np.argsort(o[:, 0])]  # spacing along canonical axes
    if model.reader == "SimpleITKIO":
        lab = predict(model, np.transpose(can, (2, 1, 0)), sp[::-1], step)
        lab = np.transpose(lab, (2, 1, 0))
    else:
        lab = predict(model, can, sp, step)
    inv = ornt.ornt_transform(ornt.axcodes2ornt(("R", "A", "S")), ornt.io_orientation(affine_mm))
    out = ornt.apply_orientation(lab, inv)
    return np.ascontiguousarray(out)
