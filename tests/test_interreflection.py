"""The ray caster's inter-reflection term (render/shading.py interreflection, render.interreflection)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from room_pipeline.errors import ConfigError
from room_pipeline.render.raycast import RaycastRenderer
from room_pipeline.render.scene import Film, TissueMaterial
from room_pipeline.render.shading import interreflection
from tests.test_raycast import MM, look, scene, tube

RED = (0.9, 0.4, 0.4)


def _render(F: float, window_mm: float = 6.0, **kw) -> dict:
    mat = TissueMaterial(base_color=RED, interreflection=F, interreflection_window_m=window_mm * MM)
    T = look([0.5 * MM, 0.0, 0.0], [0, 0, 1])
    sc = scene(tube(wobble=0.1), [T], material=mat, film=Film(exposure_ev=0.0), **kw)
    return RaycastRenderer(sc).render(0, ("rgb", "depth"))


def test_off_adds_nothing_and_on_adds_reddened_light_everywhere_on_the_wall():
    off, on = _render(0.0), _render(0.6)
    hit = off["hit"]
    assert np.array_equal(off["hit"], on["hit"])
    added = on["rgb_linear"] - off["rgb_linear"]
    assert np.all(np.isfinite(on["rgb_linear"]))
    assert np.all(added[~hit] == 0) and np.all(added[hit] > 0)
    # more bounces in the more reflective channel: the added light is redder than the albedo
    ratio = added[hit][:, 0].sum() / added[hit][:, 2].sum()
    assert ratio > RED[0] / RED[2]
    # the far (dim) walls gain relatively more than the near ones: the tube's far end brightens
    d = on["depth"][hit]
    rel = (added[hit][:, 1] / np.maximum(off["rgb_linear"][hit][:, 1], 1e-12))
    assert np.median(rel[d > np.percentile(d, 80)]) > np.median(rel[d < np.percentile(d, 20)])


def test_geometric_series_and_window():
    """A flat wall at one depth with uniform radiance x: L_ind = albedo F x / (1 - F albedo) per channel."""
    h, w = 8, 8
    direct = np.full((h, w, 3), 0.2, np.float32)
    depth = np.full((h, w), 0.01, np.float32)
    hit = np.ones((h, w), bool)
    mat = TissueMaterial(base_color=RED, interreflection=0.5)
    out = interreflection(direct, None, depth, hit, mat)
    expect = np.array(RED) * 0.5 * 0.2 / (1 - 0.5 * np.array(RED))
    assert np.allclose(out, expect[None, None, :], rtol=1e-5)
    # nothing hit, F 0: zeros
    assert not interreflection(direct, None, depth, np.zeros_like(hit), mat).any()
    assert not interreflection(direct, None, depth, hit, dataclasses.replace(mat, interreflection=0.0)).any()


@pytest.mark.parametrize("bad", [{"interreflection": 1.0}, {"interreflection": -0.1},
                                 {"interreflection_window_mm": 0.0}])
def test_bad_interreflection_config_is_refused(bad):
    from room_pipeline.render.params import RenderParams

    with pytest.raises(ConfigError, match="interreflection"):
        RenderParams.from_dict(bad)
