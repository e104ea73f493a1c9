"""Sensor-noise model of the ROOM pipeline: calibrate on real frames, synthesise on clean renders.

:mod:`.calibrate` measures a :class:`NoiseProfile` (per-channel power spectra on a fixed normalised
frequency grid, cross-channel spectra, optional intensity dependence, provenance) from a folder of
real endoscope frames; :mod:`.synthesize` draws noise with those statistics at any resolution and
adds it to 8-bit renders; :mod:`.spectrum` holds the spectral conventions (PSD normalisation,
radial averages, log-spectral distance) shared by both and by the tests and benchmark.
"""
from __future__ import annotations

from .calibrate import CalibrationParams, calibrate_folder, calibrate_images
from .profile import IntensityModel, NoiseProfile
from .synthesize import add_noise, synthesize

__all__ = ["CalibrationParams", "IntensityModel", "NoiseProfile", "add_noise", "calibrate_folder",
           "calibrate_images", "synthesize"]
