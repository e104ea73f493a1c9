"""A small U-Net for monocular depth, trained on CPU: the fine-tuning experiment of the paper's Table III.

The experiment (what "before" and "after" mean)
    The paper fine-tunes depth networks pretrained elsewhere on ROOM data and
    evaluates them before and after.  Pretrained weights of large models cannot
    be downloaded here, so the same experiment is run end to end at small
    scale, deterministically:

    * **before** = the network *pretrained* on generic synthetic endoluminal
      data: procedurally bent, bulging tubes with random radius, wall wobble,
      tissue colour, roughness, exposure and field of view, rendered with the
      project's fast renderer (:func:`synthetic_tube_set`) -- a stand-in for a
      generic pretrained model: it has seen tubes under a tip light, never an
      airway tree;
    * **after** = that network *fine-tuned* on the ROOM phantom sequences of
      the training patient (every frame but a held-out tail of each sequence).

    Both are evaluated with median scaling per sequence on (i) the held-out
    tail of the training patient's sequences, (ii) sequences of *other
    anatomy* (patients built from the shared real airway masks when the config
    has them, else other phantom seeds; absent in a one-patient config, then
    reported unavailable with the reason) and (iii) the shared SimCol
    colonoscopy RGB-D pairs as an external set (:func:`simcol_samples`).

Network
    Input: the sRGB frame resized to ``input_size`` squared (area filter),
    values /255.  A stride-2 stem, a four-level U-Net (two 3x3 conv +
    GroupNorm + ReLU per level, max-pool down, bilinear up, skip
    concatenation) and a 3x3 head give log depth at half the input
    resolution, upsampled bilinearly to ``input_size`` (~390 k parameters with
    the default channels).  The estimator returns ``exp`` of it; the
    evaluator resizes it to the ground truth (``resizes = True``).

Loss
    Per image, scale-invariant log error (Eigen et al. 2014)
    ``sqrt(mean(d^2) - lambda mean(d)^2)``, ``d = log p - log g`` on the
    pixels whose ground truth is in the valid range (targets: area-averaged
    valid depth of the downscaled frame); mean over the batch.

Determinism
    ``torch.manual_seed(seed)``, ``torch.use_deterministic_algorithms(True)``
    and ``torch.set_num_threads(threads)`` for the duration of training
    (restored after), batches drawn from ``numpy.random.default_rng(seed)``
    permutations, flips from the same generator: same data, seed and thread
    count -> the same weight bytes.  Checkpoints are ``torch.save`` of plain
    dicts into memory, then written atomically (their bytes do not depend on
    the file name).

torch is optional (``pip install 'room-pipeline[depth]'``): without it every
function that needs it raises :class:`~room_pipeline.errors.BackendUnavailable`.

The training and evaluation data (frames to tensors, the synthetic tube set, the SimCol pairs) are
:mod:`~room_pipeline.depth.cnn_data`.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import math
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from ..catalog import DEPTH_MODEL
from ..config.params import params_from_dict
from ..errors import BackendUnavailable, ConfigError, InputError
from ..io.atomic import write_bytes
from .base import Estimator, Frame
from .cnn_data import ArrayDataset, to_input
from .cnn_data import (SIMCOL_CAMERA, SIMCOL_DEPTH_M_PER_UNIT, curved_tube, dataset_from_samples,  # noqa: F401
                       read_simcol, simcol_samples, synthetic_tube_set, to_target)  # (re-exported: the CNN's API)


CHECKPOINT_FORMAT = "room-depth-cnn/1"
WHICH = ("pretrained", "finetuned")


@dataclasses.dataclass(frozen=True)
class CNNParams:
    """``depth.cnn``: the network and where evaluate_depth finds it."""

    input_size: int = 128
    channels: tuple = (16, 32, 64, 96)
    threads: int = 1
    inference_threads: int = 1
    checkpoint_patient: str = "patient_000"

    def __post_init__(self) -> None:
        if self.input_size < 16 or self.input_size % 16:
            raise ConfigError(f"depth.cnn.input_size must be a multiple of 16 (>= 16), got {self.input_size}")
        if len(self.channels) < 2 or any(int(c) < 4 or int(c) % 4 for c in self.channels):
            raise ConfigError(f"depth.cnn.channels: >= 2 levels, each a multiple of 4, got {list(self.channels)}")
        if self.threads < 1 or self.inference_threads < 1:
            raise ConfigError("depth.cnn.threads and depth.cnn.inference_threads must be >= 1")


@dataclasses.dataclass(frozen=True)
class TrainParams:
    """``depth.train``: the fine-tuning experiment (see the module docstring)."""

    seed: int = 0
    batch_size: int = 8
    pretrain_scenes: int = 32
    pretrain_views: int = 8
    pretrain_steps: int = 150
    pretrain_learning_rate: float = 1e-3
    finetune_steps: int = 250
    finetune_learning_rate: float = 5e-4
    si_lambda: float = 0.85
    train_stride: int = 1
    holdout_fraction: float = 0.2
    holdout_gap_frames: int = 10
    eval_stride: int = 5
    eval_patients: tuple | None = None
    simcol_dir: str | None = None

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "TrainParams":
        p = params_from_dict(cls, d, "depth.train")
        if p.batch_size < 1 or p.pretrain_scenes < 1 or p.pretrain_views < 1 or p.pretrain_steps < 0 \
                or p.finetune_steps < 0 or p.train_stride < 1 or p.eval_stride < 1 or p.holdout_gap_frames < 0:
            raise ConfigError("depth.train: counts must be >= 1 (steps, gap >= 0)")
        if not 0 <= p.holdout_fraction < 1 or not 0 <= p.si_lambda <= 1:
            raise ConfigError("depth.train: 0 <= holdout_fraction < 1 and 0 <= si_lambda <= 1 required")
        if p.pretrain_learning_rate <= 0 or p.finetune_learning_rate <= 0:
            raise ConfigError("depth.train: learning rates must be > 0")
        return p


# ----------------------------------------------------------------------------- torch, lazily


def require_torch():
    """The torch module, or BackendUnavailable saying how to get it."""
    try:
        import torch
    except ImportError as exc:
        raise BackendUnavailable(f"torch is not installed ({exc}); install the CPU wheel: "
                                 "pip install 'room-pipeline[depth]'") from None
    return torch


@contextlib.contextmanager
def deterministic_torch(seed: int, threads: int) -> Iterator[Any]:
    """Seeded, deterministic, fixed-thread torch for the duration of the block (restored after)."""
    torch = require_torch()
    old_threads = torch.get_num_threads()
    old_det = torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(int(threads))
    torch.use_deterministic_algorithms(True)
    torch.manual_seed(int(seed))
    try:
        yield torch
    finally:
        torch.use_deterministic_algorithms(old_det)
        torch.set_num_threads(old_threads)


_MODEL_CLASS: list = []


def _unet_class():
    """The U-Net class (defined on first use so that this module imports without torch)."""
    if _MODEL_CLASS:
        return _MODEL_CLASS[0]
    torch = require_torch()
    nn = torch.nn
    F = torch.nn.functional

    def block(c_in: int, c_out: int):
        return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1), nn.GroupNorm(4, c_out), nn.ReLU(inplace=True),
                             nn.Conv2d(c_out, c_out, 3, padding=1), nn.GroupNorm(4, c_out), nn.ReLU(inplace=True))

    class DepthUNet(nn.Module):
        """(B, 3, S, S) in [0, 1] -> (B, S, S) log depth (metres up to the training's scale)."""

        def __init__(self, channels: Sequence[int]) -> None:
            super().__init__()
            ch = [int(c) for c in channels]
            self.stem = nn.Sequential(nn.Conv2d(3, ch[0], 3, stride=2, padding=1), nn.ReLU(inplace=True))
            self.enc = nn.ModuleList()
            c_in = ch[0]
            for c in ch:
                self.enc.append(block(c_in, c))
                c_in = c
            self.dec = nn.ModuleList()
            for c_skip in reversed(ch[:-1]):
                self.dec.append(block(c_in + c_skip, c_skip))
                c_in = c_skip
            self.head = nn.Conv2d(c_in, 1, 3, padding=1)
            with torch.no_grad():
                self.head.bias.fill_(math.log(0.03))          # start near a few centimetres

        def forward(self, x):
            size = x.shape[-2:]
            x = self.stem(x)
            skips = []
            for i, b in enumerate(self.enc):
                if i:
                    x = F.max_pool2d(x, 2)
                x = b(x)
                skips.append(x)
            for b, skip in zip(self.dec, reversed(skips[:-1])):
                x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
                x = b(torch.cat([x, skip], 1))
            x = F.interpolate(self.head(x), size=size, mode="bilinear", align_corners=False)
            return x[:, 0]

    _MODEL_CLASS.append(DepthUNet)
    return DepthUNet


def build_model(channels: Sequence[int]):
    """A freshly initialised U-Net (uses torch's current RNG state: seed it first)."""
    return _unet_class()(channels)


def n_parameters(model) -> int:
    return int(sum(p.numel() for p in model.parameters()))


def si_log_loss(torch, pred_log, target, lam: float):
    """Mean over images of sqrt(mean d^2 - lam mean(d)^2), d = pred_log - log target on target > 0."""
    m = (target > 0).to(pred_log.dtype)
    n = m.sum(dim=(1, 2))
    d = (pred_log - torch.log(torch.clamp(target, min=1e-6))) * m
    m1 = d.sum(dim=(1, 2)) / torch.clamp(n, min=1.0)
    # mean d^2 - lam mean(d)^2 = mean (d - mean d)^2 + (1 - lam) mean(d)^2: the centred form, because the
    # one-pass difference cancels in float32 (a pure scale error left sqrt(~3e-8) = 1.7e-4 instead of 0)
    c = (d - m1[:, None, None]) * m
    var = (c * c).sum(dim=(1, 2)) / torch.clamp(n, min=1.0)
    per = torch.sqrt(torch.clamp(var + (1.0 - lam) * m1 * m1, min=1e-12))
    used = (n > 0).to(pred_log.dtype)
    return (per * used).sum() / torch.clamp(used.sum(), min=1.0)


def train_steps(model, data: ArrayDataset, steps: int, lr: float, batch_size: int, seed: int, si_lambda: float,
                log: Callable[[int, float], None] | None = None) -> list[float]:
    """Adam with a cosine learning-rate decay (to lr/10) for ``steps`` batches; returns the losses.

    Batches walk through seeded permutations of the data; each image is
    flipped horizontally with probability 1/2 (same generator).  Call inside
    :func:`deterministic_torch`.
    """
    torch = require_torch()
    if len(data) == 0 or steps == 0:
        return []
    rng = np.random.default_rng(seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    model.train()
    order: list[int] = []
    losses = []
    for step in range(steps):
        while len(order) < batch_size:
            order.extend(rng.permutation(len(data)).tolist())
        idx, order = order[:batch_size], order[batch_size:]
        flip = rng.random(len(idx)) < 0.5
        x = data.x[idx].copy()
        y = data.y[idx].copy()
        x[flip] = x[flip][..., ::-1]
        y[flip] = y[flip][..., ::-1]
        for g in opt.param_groups:
            g["lr"] = lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * step / max(steps, 1))))
        loss = si_log_loss(torch, model(torch.from_numpy(np.ascontiguousarray(x))),
                           torch.from_numpy(np.ascontiguousarray(y)), si_lambda)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        if log is not None:
            log(step, losses[-1])
    model.eval()
    return losses


# ----------------------------------------------------------------------------- checkpoints


def checkpoint_path(output_dir: str | Path, patient: str, which: str) -> Path:
    """``<output_dir>/<patient>/depth_model/<which>.pt`` (which: pretrained | finetuned)."""
    if which not in WHICH:
        raise ValueError(f"which must be one of {WHICH}")
    return Path(output_dir) / patient / DEPTH_MODEL / f"{which}.pt"


def checkpoint_bytes(model, channels: Sequence[int], input_size: int, meta: Mapping[str, Any]) -> bytes:
    """The checkpoint as bytes (independent of any file name): format, architecture, weights, provenance.

    ``meta`` goes through JSON (plain types only), so the file loads with ``weights_only=True``.
    """
    torch = require_torch()
    buf = io.BytesIO()
    state = {k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}
    torch.save({"format": CHECKPOINT_FORMAT, "channels": [int(c) for c in channels], "input_size": int(input_size),
                "state_dict": state, "meta": json.loads(json.dumps(dict(meta), default=str))}, buf)
    return buf.getvalue()


def save_checkpoint(path: str | Path, model, channels: Sequence[int], input_size: int,
                    meta: Mapping[str, Any]) -> str:
    """Write atomically; returns the sha256 of the bytes."""
    data = checkpoint_bytes(model, channels, input_size, meta)
    write_bytes(path, data)
    return hashlib.sha256(data).hexdigest()


def load_checkpoint(path: str | Path) -> tuple[Any, dict]:
    """(model in eval mode, checkpoint dict without the weights); InputError on a foreign or broken file."""
    torch = require_torch()
    path = Path(path)
    if not path.is_file():
        raise BackendUnavailable(f"no trained CNN checkpoint at {path} (run the train_depth stage)")
    try:
        ck = torch.load(io.BytesIO(path.read_bytes()), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many types for a broken file
        raise InputError(f"{path}: not a readable torch checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        raise InputError(f"{path}: not a room depth CNN checkpoint (format {CHECKPOINT_FORMAT} expected)")
    model = build_model(ck["channels"])
    model.load_state_dict(ck["state_dict"])
    model.eval()
    return model, {k: v for k, v in ck.items() if k != "state_dict"}


# ----------------------------------------------------------------------------- estimator


def predict_depth(model, rgb8: np.ndarray, size: int) -> np.ndarray:
    """(size, size) float32 depth (exp of the network's log depth)."""
    torch = require_torch()
    x = torch.from_numpy(to_input(rgb8, size)[None])
    with torch.no_grad():
        out = model(x)[0].numpy()
    return np.exp(out).astype(np.float32)


class CNNEstimator(Estimator):
    """The trained U-Net; answers at its input size (``resizes``), evaluated median-scaled."""

    scaling = "median"
    resizes = True

    def __init__(self, name: str, model, info: Mapping[str, Any], threads: int, path: Path | None = None) -> None:
        self.name, self.model, self.info, self.threads, self.path = name, model, dict(info), int(threads), path
        self.size = int(self.info["input_size"])

    @classmethod
    def load(cls, name: str, path: str | Path, params: CNNParams) -> "CNNEstimator":
        model, info = load_checkpoint(path)
        return cls(name, model, info, params.inference_threads, Path(path))

    def predict(self, frame: Frame) -> np.ndarray:
        torch = require_torch()
        if torch.get_num_threads() != self.threads:      # re-sizing the thread pool per call is costly
            torch.set_num_threads(self.threads)
        return predict_depth(self.model, frame.rgb, self.size)

    def describe(self) -> dict:
        d = {"checkpoint": str(self.path) if self.path else None, "input_size": self.size,
             "channels": self.info.get("channels"), "meta": self.info.get("meta", {})}
        if self.path is not None and self.path.is_file():
            d["checkpoint_sha256"] = hashlib.sha256(self.path.read_bytes()).hexdigest()
        return d


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0
