"""Parameters of the airway segmentation (``conf/segment/default.yaml``: HU, millimetres) and its result
record (:mod:`~room_pipeline.anatomy.segment`)."""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from ..config.params import params_from_dict
from ..errors import ConfigError
from ..io.volume import Volume


METHODS = ("region_growing", "totalsegmentator")
DENOISE = ("gaussian", "median", "none")
#: TotalSegmentator task, its weights folder and the airway class label in its multilabel output
TS_TASK = "lung_vessels"
TS_DATASET = "Dataset258_lung_vessels_248subj"
TS_AIRWAY_NAME = "lung_trachea_bronchia"  # its label is read from the model's dataset.json (2 in Dataset258)


@dataclasses.dataclass
class SegmentParams:
    """Knobs of :func:`segment_airways`; field names are the keys of ``conf/segment/<method>.yaml``.

    HU values are Hounsfield units, ``*_mm`` lengths millimetres, ``*_ml`` volumes millilitres.
    """

    method: str = "region_growing"
    #: HU below which a voxel is air (trachea search, input checks)
    air_hu: float = -900.0
    #: denoising before growing: gaussian | median (3x3x3) | none
    denoise: str = "gaussian"
    #: Gaussian sigma (mm), per axis converted to voxels
    smoothing_sigma_mm: float = 0.5
    #: depth below the top of the volume searched for the trachea (mm)
    seed_search_depth_mm: float = 80.0
    #: a trachea candidate must persist this far downwards (mm)
    seed_track_mm: float = 5.0
    #: accepted equivalent diameter of the trachea cross-section (mm)
    trachea_min_diameter_mm: float = 8.0
    trachea_max_diameter_mm: float = 30.0
    #: minimum minor/major axis ratio of the trachea cross-section
    trachea_min_roundness: float = 0.5
    #: maximum left-right distance of the trachea from the body centre (mm)
    trachea_max_offset_mm: float = 40.0
    #: adaptive threshold sweep (HU): start, coarse step, fine step, upper limit
    threshold_start_hu: float = -950.0
    threshold_step_hu: float = 20.0
    threshold_fine_step_hu: float = 5.0
    threshold_max_hu: float = -500.0
    #: a step whose volume exceeds leak_factor x the previous one is a leak
    leak_factor: float = 1.5
    #: leak checks start once the region holds this much (ml)
    min_volume_ml: float = 0.2
    #: any region larger than this is a leak (ml)
    max_volume_ml: float = 600.0
    #: region-growing connectivity: 6 (faces) or 26 (faces, edges, corners)
    connectivity: int = 6
    #: boundary refinement: add partial-volume voxels below this HU (null: off)
    refine_hu: float | None = -500.0
    #: number of refinement layers (each at most one voxel)
    refine_layers: int = 1
    #: one-voxel airways: also follow raw-CT voxels below this HU (null: off)
    thin_airway_hu: float | None = -950.0
    #: fill cavities enclosed by the lumen mask
    fill_holes: bool = True
    #: TotalSegmentator only: folder with its weights (else env TOTALSEG_HOME_DIR)
    weights_dir: str | None = None
    #: TotalSegmentator only: 'cpu', 'gpu' or 'gpu:N'
    device: str = "cpu"

    def __post_init__(self) -> None:
        self.validate()

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "SegmentParams":
        """Build from a config mapping (:func:`~room_pipeline.config.params.params_from_dict`: ``refine_hu``,
        ``thin_airway_hu`` and ``weights_dir`` may be null; then :meth:`validate` in :meth:`__post_init__`);
        unknown keys or invalid values raise :class:`ConfigError` naming the key."""
        return params_from_dict(cls, d, "segment")

    def validate(self) -> None:
        """Raise :class:`ConfigError` on an inconsistent value."""
        def bad(key: str, why: str) -> ConfigError:
            return ConfigError(f"segment.{key}={getattr(self, key)!r}: {why}")
        if self.method not in METHODS:
            raise bad("method", f"must be one of {', '.join(METHODS)}")
        if self.denoise not in DENOISE:
            raise bad("denoise", f"must be one of {', '.join(DENOISE)}")
        if self.connectivity not in (6, 26):
            raise bad("connectivity", "must be 6 or 26")
        for k in ("threshold_step_hu", "threshold_fine_step_hu", "trachea_min_diameter_mm",
                  "seed_search_depth_mm", "max_volume_ml"):
            if not getattr(self, k) > 0:
                raise bad(k, "must be > 0")
        for k in ("smoothing_sigma_mm", "seed_track_mm", "min_volume_ml", "refine_layers",
                  "trachea_max_offset_mm"):
            if getattr(self, k) < 0:
                raise bad(k, "must be >= 0")
        if self.trachea_max_diameter_mm < self.trachea_min_diameter_mm:
            raise bad("trachea_max_diameter_mm", "must be >= trachea_min_diameter_mm")
        if not 0 < self.trachea_min_roundness <= 1:
            raise bad("trachea_min_roundness", "must be in (0, 1]")
        if self.threshold_max_hu < self.threshold_start_hu:
            raise bad("threshold_max_hu", "must be >= threshold_start_hu")
        if not self.leak_factor > 1:
            raise bad("leak_factor", "must be > 1")


@dataclasses.dataclass
class SegmentResult:
    """Output of :func:`segment_airways`.

    Attributes:
        mask: uint8 0/1 airway lumen on the CT grid.
        seed: trachea seed voxel (i, j, k).
        threshold_hu: the last safe region-growing threshold (HU; NaN for TotalSegmentator).
        report: JSON-serialisable diagnostics.
    """

    mask: Volume
    seed: tuple[int, int, int]
    threshold_hu: float
    report: dict
