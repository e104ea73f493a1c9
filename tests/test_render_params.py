"""The render section's Cycles preset and pixel-filter keys (conf/render/default.yaml -> RenderParams)."""
from __future__ import annotations

import pytest

from room_pipeline.config.compose import compose, section
from room_pipeline.errors import ConfigError
from room_pipeline.render.params import RenderParams, cycles_settings, raycast_config


def default_render() -> dict:
    return dict(section(compose(), "render"))


def test_cycles_preset_takes_its_bounces_from_the_config():
    p = RenderParams.from_dict(default_render())
    st = cycles_settings(p)
    assert st.max_bounces == p.cycles_bounces == 8 and st.samples == p.cycles_samples and st.denoise
    assert cycles_settings(RenderParams.from_dict({**default_render(), "cycles_bounces": 3})).max_bounces == 3
    for bad in (-1, 2.5, True, "8"):
        with pytest.raises(ConfigError, match="cycles_bounces"):
            RenderParams.from_dict({**default_render(), "cycles_bounces": bad})


def test_edge_samples_reach_the_ray_caster():
    p = RenderParams.from_dict({**default_render(), "edge_samples": 4, "edge_depth_jump": 0.2})
    cfg = raycast_config(p)
    assert cfg.edge_samples == 4 and cfg.edge_depth_jump == 0.2
    for k, bad in (("edge_samples", -1), ("edge_samples", 1.5), ("edge_depth_jump", 0.0)):
        with pytest.raises(ConfigError, match="edge_"):
            RenderParams.from_dict({**default_render(), k: bad})
