"""Adapters for Hugging Face ``transformers`` depth models (Depth Anything V2, DPT, ZoeDepth) from a local folder.

Each ``depth.hf.<name>`` entry names a folder holding what ``save_pretrained``
writes (``config.json``, the weights, ``preprocessor_config.json``); the model
loads with ``AutoModelForDepthEstimation.from_pretrained(path)`` and its image
processor with ``AutoImageProcessor.from_pretrained(path)``, both
``local_files_only`` (nothing is downloaded).  Get the weights elsewhere, e.g.::

    huggingface-cli download depth-anything/Depth-Anything-V2-Small-hf --local-dir models/hf/depth-anything-v2-small

Outputs
    ``output: disparity`` -- relative inverse depth (Depth Anything V2
    relative checkpoints, DPT/MiDaS): depth = 1 / disparity, then median-scaled
    per sequence (the affine shift of such models is ignored, as in the
    paper's protocol); ``output: depth`` -- depth in ``depth_unit_m`` metres
    per unit (ZoeDepth, Depth Anything V2 metric checkpoints): ``scaling:
    metric`` (also reported median-scaled).  The prediction is brought to the
    frame's size by the processor's ``post_process_depth_estimation`` (bilinear).

transformers and torch are optional (``pip install 'room-pipeline[depth]'``);
missing packages or weights raise :class:`~room_pipeline.errors.BackendUnavailable`.
"""
from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..config.params import params_from_dict
from ..errors import BackendUnavailable, ConfigError
from .base import SCALINGS, Estimator, Frame

OUTPUTS = ("disparity", "depth")


@dataclasses.dataclass(frozen=True)
class HFModelSpec:
    """One ``depth.hf.<name>`` entry."""

    path: str = ""
    output: str = "disparity"
    scaling: str = "median"
    depth_unit_m: float = 1.0
    threads: int = 1
    hub_id: str = ""

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, section: str = "depth.hf") -> "HFModelSpec":
        p = params_from_dict(cls, d, section)
        if not p.path:
            raise ConfigError(f"{section}.path: the local model folder is required")
        if p.output not in OUTPUTS or p.scaling not in SCALINGS:
            raise ConfigError(f"{section}: output must be one of {OUTPUTS} and scaling one of {SCALINGS}")
        if p.output == "disparity" and p.scaling == "metric":
            raise ConfigError(f"{section}: a disparity (relative) output cannot be metric")
        if p.depth_unit_m <= 0 or p.threads < 1:
            raise ConfigError(f"{section}: depth_unit_m > 0 and threads >= 1 required")
        return p


def _require():
    try:
        import torch
        import transformers
    except ImportError as exc:
        raise BackendUnavailable(f"Hugging Face depth models need torch and transformers ({exc}): "
                                 "pip install 'room-pipeline[depth]'") from None
    return torch, transformers


class HFDepthEstimator(Estimator):
    """A ``transformers`` depth-estimation model loaded from a local folder."""

    def __init__(self, name: str, spec: HFModelSpec) -> None:
        self.name, self.spec = name, spec
        self.scaling = spec.scaling
        path = Path(spec.path)
        if not (path / "config.json").is_file():
            how = f"; e.g. huggingface-cli download {spec.hub_id} --local-dir {path}" if spec.hub_id else ""
            raise BackendUnavailable(f"{name}: no model weights at {path} (config.json missing; nothing is "
                                     f"downloaded here{how})")
        torch, transformers = _require()
        self._torch = torch
        try:
            self.processor = transformers.AutoImageProcessor.from_pretrained(str(path), local_files_only=True)
            self.model = transformers.AutoModelForDepthEstimation.from_pretrained(str(path), local_files_only=True)
        except (OSError, ValueError, KeyError) as exc:
            raise BackendUnavailable(f"{name}: cannot load the model at {path}: {str(exc).splitlines()[0]}") from None
        self.model.eval()
        post = getattr(self.processor, "post_process_depth_estimation", None)
        self._post_params = set(inspect.signature(post).parameters) if post is not None else set()

    def _to_size(self, outputs, h: int, w: int):
        """The prediction at (h, w): the processor's own post-processing, else the same steps here.

        The fallback exists because transformers' PIL-backend ZoeDepth processor
        calls torchvision in ``post_process_depth_estimation`` (5.23: NameError
        without torchvision, which is not installed with the CPU torch wheel).
        """
        torch = self._torch
        if "target_sizes" in self._post_params:
            kw: dict[str, Any] = {"target_sizes": [(h, w)]}
            if "source_sizes" in self._post_params:          # ZoeDepth: removes its padding first
                kw["source_sizes"] = [(h, w)]
            try:
                return self.processor.post_process_depth_estimation(outputs, **kw)[0]["predicted_depth"]
            except (NameError, ImportError):
                pass
        pred = outputs.predicted_depth[:, None].float()
        interp = torch.nn.functional.interpolate
        if "source_sizes" in self._post_params and getattr(self.processor, "do_pad", False):
            # ZoeDepth pads each side by int(sqrt(size / 2) * 3) before the network; undo it
            ph, pw = int(np.sqrt(h / 2) * 3), int(np.sqrt(w / 2) * 3)
            pred = interp(pred, size=(h + 2 * ph, w + 2 * pw), mode="bicubic", align_corners=False)
            pred = pred[:, :, ph: ph + h, pw: pw + w]
        return interp(pred, size=(h, w), mode="bilinear", align_corners=False)[0, 0]

    def predict(self, frame: Frame) -> np.ndarray:
        torch = self._torch
        rgb = np.ascontiguousarray(frame.rgb[..., :3])
        h, w = rgb.shape[:2]
        if torch.get_num_threads() != self.spec.threads:
            torch.set_num_threads(self.spec.threads)
        with torch.no_grad():
            inputs = self.processor(images=rgb, return_tensors="pt")
            outputs = self.model(**inputs)
            pred = self._to_size(outputs, h, w)
        p = pred.detach().float().cpu().numpy().reshape(h, w).astype(np.float64)
        if self.spec.output == "disparity":
            with np.errstate(divide="ignore", invalid="ignore"):
                p = np.where(p > 0, 1.0 / p, np.nan)
        else:
            p = p * self.spec.depth_unit_m
        return p.astype(np.float32)

    def describe(self) -> dict:
        cfg = self.model.config
        return {"path": self.spec.path, "hub_id": self.spec.hub_id or None, "model_type": cfg.model_type,
                "architectures": list(getattr(cfg, "architectures", None) or []), "output": self.spec.output,
                "n_parameters": int(sum(p.numel() for p in self.model.parameters()))}
