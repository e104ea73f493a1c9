"""PyTorch ``Dataset`` over rendered ROOM sequences (the only module of the project that imports torch).

Usage::

    from room_pipeline.dataset import RoomDataset, room_collate
    ds = RoomDataset("data/output", modalities=["rgb", "depth", "flow"])        # every sequence found
    loader = torch.utils.data.DataLoader(ds, batch_size=8, shuffle=True)
    pairs = RoomDataset("data/output/patient_000/sequence_001", ["rgb", "depth"], pairs=True)

One item (``pairs=False``) is a dict of tensors, the :class:`~room_pipeline.dataset.SequenceReader`
frame converted to channels-first float layout (H, W: image size):

    ``rgb``, ``rgb_noisy``   (3, H, W) float32 in [0, 1] (sRGB values / 255, not linearised)
    ``depth``                (1, H, W) float32 planar z, metres, 0 = no hit
    ``relative_depth``       (1, H, W) float32 normalised inverse depth in [0, 1], 0 = no hit;
                             ``relative_depth_range`` (2,) float64 [d_min, d_max] metres
    ``normals``              (3, H, W) float32 unit normals, OpenCV camera frame, 0 = no hit
    ``flow``                 (2, H, W) float32 forward flow t -> t+1, pixels (u along columns, v along rows)
    ``flow_valid``, ``valid`` (1, H, W) bool (flow correspondence valid; surface hit)
    ``segmentation``         (1, H, W) int64 label = airway branch id + 1, 0 = no hit
    ``point_cloud``          (N, 3) float32 camera-frame metres (+ ``point_cloud_normals`` (N, 3)
                             float32, ``point_cloud_colors`` (N, 3) uint8): N varies per frame, so
                             batch them with :func:`room_collate` (keeps them as lists)
    ``pose``                 (4, 4) float64 camera-to-world (world RAS+ metres, OpenCV camera:
                             x right, y down, z forward)
    ``K``                    (3, 3) float64 pinhole matrix (pixel centres at integer coordinates,
                             top-left pixel centre (0, 0)); ``intrinsics`` (4,) float64 (fx, fy, cx, cy)
    ``timestamp``            () float64 seconds; ``index`` () int64 frame number;
    ``name`` str (``frame_NNNN``); ``sequence`` str (the sequence folder)

With ``pairs=True`` an item is ``{"t": frame t, "t1": frame t+1, "T_t1_t": (4, 4) float64,
"sequence": str}`` for every consecutive pair of a sequence (len - 1 per sequence), with
``T_t1_t = inv(pose_t1) @ pose_t`` mapping camera-t coordinates to camera-(t+1) coordinates
(:func:`room_pipeline.render.flow.relative_pose`): the forward flow of frame t is the projection
of ``T_t1_t @ (depth_t K^-1 [u, v, 1])`` minus ``(u, v)``.  ``transform``, when given, is called on
each item (the dict above) and returns the item to use.
"""
from __future__ import annotations

import bisect
import os
from typing import Any, Callable, Iterable, Sequence, Union

import numpy as np

from ..catalog import RGB_NOISY, RGB_SOURCES
from ..errors import BackendUnavailable, InputError
from .reader import SequenceReader, find_sequences

try:
    import torch
    from torch.utils.data import Dataset, default_collate
except ImportError as _exc:  # pragma: no cover - exercised by a test that hides torch
    raise BackendUnavailable("RoomDataset needs PyTorch, which is not installed (pip install torch); "
                             "room_pipeline.dataset.SequenceReader reads the same data with NumPy only") from _exc

#: keys whose first dimension varies from frame to frame (kept as lists by :func:`room_collate`)
VARIABLE_SIZE = ("point_cloud", "point_cloud_normals", "point_cloud_colors")
_CHW = {"rgb": 3, RGB_NOISY: 3, "normals": 3, "flow": 2}
_PLANES = ("depth", "relative_depth", "flow_valid", "valid")

Source = Union[str, os.PathLike, SequenceReader]


def frame_to_tensors(frame: dict[str, Any], sequence: str = "") -> dict[str, Any]:
    """A :meth:`SequenceReader.frame` dict -> the tensor dict documented in the module docstring."""
    out: dict[str, Any] = {}
    for k, v in frame.items():
        if k in RGB_SOURCES:
            out[k] = torch.from_numpy(np.ascontiguousarray(v.transpose(2, 0, 1))).to(torch.float32).div_(255.0)
        elif k in _CHW:
            out[k] = torch.from_numpy(np.ascontiguousarray(v.transpose(2, 0, 1)))
        elif k in _PLANES:
            out[k] = torch.from_numpy(np.ascontiguousarray(v))[None]
        elif k == "segmentation":
            out[k] = torch.from_numpy(v.astype(np.int64))[None]
        elif k in VARIABLE_SIZE or k in ("pose", "K", "relative_depth_range"):
            out[k] = torch.from_numpy(np.array(v))
        elif k == "intrinsics":
            out[k] = torch.tensor([v["fx"], v["fy"], v["cx"], v["cy"]], dtype=torch.float64)
        elif k == "timestamp":
            out[k] = torch.tensor(v, dtype=torch.float64)
        elif k == "index":
            out[k] = torch.tensor(v, dtype=torch.int64)
        else:
            out[k] = v
    out["sequence"] = sequence
    return out


class RoomDataset(Dataset):
    """Frames (or consecutive frame pairs) of one or many rendered sequences as tensor dicts.

    ``sources``: a folder (a dataset root, a patient folder or a sequence: every sequence found by
    :func:`~room_pipeline.dataset.find_sequences`), a :class:`SequenceReader`, or a list of these,
    in order.  ``modalities``: as for :class:`SequenceReader` (None: its default set); readers
    passed in are re-opened with them when given.  ``pairs``: items are (t, t+1) pairs.
    ``transform``: optional callable item -> item.
    """

    def __init__(self, sources: Union[Source, Sequence[Source]], modalities: Iterable[str] | None = None,
                 pairs: bool = False, transform: Callable[[dict], dict] | None = None) -> None:
        if isinstance(sources, (str, os.PathLike, SequenceReader)):
            sources = [sources]
        mods = None if modalities is None else list(modalities)
        readers: list[SequenceReader] = []
        for s in sources:
            if isinstance(s, SequenceReader):
                readers.append(s if mods is None else SequenceReader(s.path, mods))
                continue
            found = find_sequences(s)
            if not found:
                raise InputError(f"no rendered sequence (metadata/render.json) under {s}")
            readers.extend(SequenceReader(p, mods) for p in found)
        if not readers:
            raise InputError("RoomDataset: no sequences given")
        self.readers = readers
        self.pairs = bool(pairs)
        self.transform = transform
        counts = [max(len(r) - 1, 0) if self.pairs else len(r) for r in readers]
        self._starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64).tolist()
        if self._starts[-1] == 0:
            raise InputError("RoomDataset: no frame pairs (every sequence has a single frame)")

    def __len__(self) -> int:
        return int(self._starts[-1])

    def locate(self, idx: int) -> tuple[int, int]:
        """Item index -> (sequence number, frame position in it)."""
        n = len(self)
        i = int(idx)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"item {idx} out of range for {n} items")
        s = bisect.bisect_right(self._starts, i) - 1
        return s, i - self._starts[s]

    def __getitem__(self, idx: int) -> dict[str, Any]:
        s, j = self.locate(idx)
        r = self.readers[s]
        seq = str(r.path)
        if self.pairs:
            f0, f1 = r.frame(j), r.frame(j + 1)
            rel = np.linalg.inv(f1["pose"]) @ f0["pose"]
            item = {"t": frame_to_tensors(f0, seq), "t1": frame_to_tensors(f1, seq),
                    "T_t1_t": torch.from_numpy(rel), "sequence": seq}
        else:
            item = frame_to_tensors(r.frame(j), seq)
        return self.transform(item) if self.transform is not None else item


def room_collate(batch: list) -> Any:
    """``default_collate``, except that point-cloud entries (variable N) stay lists of tensors."""
    if batch and isinstance(batch[0], dict):
        out = {}
        for k in batch[0]:
            vals = [b[k] for b in batch]
            out[k] = vals if k in VARIABLE_SIZE else room_collate(vals)
        return out
    return default_collate(batch)
