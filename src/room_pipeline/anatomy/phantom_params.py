"""Parameters of the procedural phantom (``conf/phantom/default.yaml``; millimetres, degrees, HU) and the
airway wall-thickness rule (:mod:`~room_pipeline.anatomy.phantom`)."""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from ..config.params import params_from_dict
from ..conventions import MM
from ..errors import ConfigError


@dataclasses.dataclass
class PhantomParams:
    """All knobs of the phantom; field names are the keys of ``conf/phantom/default.yaml``.

    Lengths in millimetres, angles in degrees, intensities in HU.
    """

    # --- tree: anatomical start
    trachea_diameter_mm: float = 17.0
    trachea_length_mm: float = 110.0
    rmb_angle_deg: float = 25.0            # right main bronchus, angle to the tracheal axis
    lmb_angle_deg: float = 45.0
    rmb_length_mm: float = 25.0
    lmb_length_mm: float = 50.0
    # --- tree: Kitaoka growth
    flow_exponent: float = 2.8             # n in d = d0 r^(1/n)
    length_to_diameter: float = 3.0
    min_diameter_mm: float = 2.0
    max_generation: int = 20
    min_branch_clearance_mm: float = 1.5   # lumen gap kept between non-adjacent branches
    min_branch_length_mm: float = 2.0      # a branch shortened for clearance stays >= max(this, diameter)
    min_region_points: int = 8
    plane_rotation_jitter_deg: float = 20.0
    lung_points: int = 20000               # both lungs together
    # --- lung / body geometry
    lung_width_mm: float = 100.0           # right lung, left-right extent
    left_lung_width_ratio: float = 0.85    # left lung narrower (heart)
    lung_depth_mm: float = 110.0           # antero-posterior extent
    lung_height_mm: float = 140.0          # base to apex
    lung_apex_above_carina_mm: float = 20.0
    mediastinum_half_width_mm: float = 18.0
    chest_wall_mm: float = 12.0            # lung surface to skin
    fat_thickness_mm: float = 5.0          # subcutaneous fat rim
    # --- grid
    spacing_mm: tuple = (0.7, 0.7, 0.7)    # voxel size along x (R), y (A), z (S)
    margin_mm: float = 10.0
    crop_top_mm: float = 0.0               # >0: volume top this far below the trachea top (trachea cut)
    sdf_band_mm: float = 5.0
    # --- intensities
    hu_air: float = -1000.0
    hu_wall: float = 40.0
    hu_parenchyma: float = -850.0
    hu_soft_tissue: float = 40.0
    hu_fat: float = -100.0
    wall_thickness_ratio: float = 0.15     # x lumen diameter
    wall_thickness_offset_mm: float = 0.3
    texture_sigma_hu: float = 25.0
    texture_correlation_mm: float = 2.0
    psf_sigma_voxels: float = 0.7
    noise_sigma_hu: float = 20.0

    def __post_init__(self) -> None:
        sp = self.spacing_mm
        if isinstance(sp, (int, float)):
            sp = (sp, sp, sp)
        try:
            sp = tuple(float(v) for v in sp)
        except (TypeError, ValueError):
            raise ConfigError(f"phantom.spacing_mm must be a number or 3 numbers, got {self.spacing_mm!r}") from None
        if len(sp) != 3 or min(sp) <= 0:
            raise ConfigError(f"phantom.spacing_mm must be 1 or 3 positive numbers (mm), got {self.spacing_mm!r}")
        self.spacing_mm = sp
        for f in dataclasses.fields(self):
            if f.name == "spacing_mm":
                continue
            v = getattr(self, f.name)
            want = int if f.type in ("int", int) else float
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(f"phantom.{f.name} must be a number, got {v!r}")
            if want is int and float(v) != int(v):
                raise ConfigError(f"phantom.{f.name} must be an integer, got {v!r}")
            setattr(self, f.name, want(v))
        positive = ("trachea_diameter_mm", "trachea_length_mm", "rmb_length_mm", "lmb_length_mm",
                    "flow_exponent", "length_to_diameter", "min_diameter_mm", "lung_points",
                    "lung_width_mm", "left_lung_width_ratio", "lung_depth_mm", "lung_height_mm",
                    "sdf_band_mm", "texture_correlation_mm")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(f"phantom.{name} must be > 0, got {getattr(self, name)}")
        nonneg = ("margin_mm", "crop_top_mm", "chest_wall_mm", "fat_thickness_mm", "mediastinum_half_width_mm",
                  "wall_thickness_ratio", "wall_thickness_offset_mm", "texture_sigma_hu",
                  "psf_sigma_voxels", "noise_sigma_hu", "plane_rotation_jitter_deg", "max_generation",
                  "min_branch_clearance_mm", "min_branch_length_mm")
        for name in nonneg:
            if getattr(self, name) < 0:
                raise ConfigError(f"phantom.{name} must be >= 0, got {getattr(self, name)}")
        if self.fat_thickness_mm > self.chest_wall_mm:
            raise ConfigError("phantom.fat_thickness_mm must not exceed phantom.chest_wall_mm")
        if self.min_region_points < 2:
            raise ConfigError(f"phantom.min_region_points must be >= 2, got {self.min_region_points}")
        if not 0 < self.rmb_angle_deg < 90 or not 0 < self.lmb_angle_deg < 90:
            raise ConfigError("phantom.rmb_angle_deg / lmb_angle_deg must be in (0, 90)")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "PhantomParams":
        """Build from a config section (:func:`~room_pipeline.config.params.params_from_dict`, then
        :meth:`__post_init__`); an unknown key or a bad value raises :class:`ConfigError` naming it."""
        return params_from_dict(cls, d, "phantom")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["spacing_mm"] = list(self.spacing_mm)
        return d


def wall_thickness(radius: np.ndarray | float, params: PhantomParams) -> np.ndarray | float:
    """Airway wall thickness (metres) for a lumen radius (metres)."""
    return params.wall_thickness_ratio * 2.0 * np.asarray(radius) + params.wall_thickness_offset_mm * MM
