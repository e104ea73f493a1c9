"""Reading a composed params file: the C-parsed loader gives OmegaConf.load's config; a bad file is one line."""
from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from room_pipeline.config.compose import load_params, load_yaml
from room_pipeline.errors import InputError

REPO = Path(__file__).resolve().parents[1]

TRICKY = """\
a:
  small: 1e-3           # OmegaConf reads this as a float (PyYAML's YAML 1.1 rule would make it a string)
  big: 2.5E+4
  int: 7
  neg: -0.5
  inf: .inf
  nan: .nan
  when: 2001-12-14      # no timestamps: stays a string
  none: null
  flag: true
  path: ${b.name}/x
  list: [1, 2.0, '3', 1e-12]
b:
  name: out
  nested: {k: [a, {z: 1}]}
"""


@pytest.mark.parametrize("source", ["params", "tricky"])
def test_same_config_as_omegaconf_load(source, tmp_path):
    path = REPO / "params.yaml" if source == "params" else tmp_path / "t.yaml"
    if source == "tricky":
        path.write_text(TRICKY, encoding="utf-8")
    a, b = OmegaConf.load(path), load_yaml(path)
    assert OmegaConf.to_yaml(a) == OmegaConf.to_yaml(b)           # (a == b is False with a NaN inside)
    assert source == "tricky" or a == b
    if source == "tricky":
        assert b.a.small == 1e-3 and isinstance(b.a.when, str) and b.a.path == "out/x"
        assert load_params(path).a.path == "out/x"


@pytest.mark.parametrize("text, pattern", [
    ("a: [1, 2\n", r"not valid YAML \(line 2, column 1\)"),
    ("a: 1\na: 2\n", r"found duplicate key a"),
    ("- 1\n- 2\n", r"expected a mapping of config sections, got list"),
])
def test_bad_params_file_is_one_input_error(text, pattern, tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(InputError, match=pattern) as e:
        load_params(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_empty_params_file_is_an_empty_config(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text("", encoding="utf-8")
    assert OmegaConf.to_container(load_yaml(path)) == {}
