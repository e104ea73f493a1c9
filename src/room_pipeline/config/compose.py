"""Compose the Hydra config tree ``conf/`` and read the composed ``params.yaml``.

``conf/`` is the single source of truth.  ``params.yaml`` is its composition,
written by :func:`write_params` with exactly the code DVC uses for
``dvc exp run`` (``dvc.utils.hydra.compose_and_dump``), so both give the same
bytes and a test can tell when ``params.yaml`` is stale.
"""
from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

from omegaconf import DictConfig, OmegaConf

from ..errors import ConfigError, InputError
from .params import params_from_dict

CONFIG_NAME = "config"


def find_conf_dir(start: str | os.PathLike | None = None) -> Path:
    """The ``conf/`` folder of the project containing ``start`` (default: cwd) or ``$ROOM_CONF_DIR``."""
    env = os.environ.get("ROOM_CONF_DIR")
    if env:
        p = Path(env).resolve()
        if not (p / f"{CONFIG_NAME}.yaml").is_file():
            raise ConfigError(f"ROOM_CONF_DIR={env} holds no {CONFIG_NAME}.yaml")
        return p
    here = Path(start or Path.cwd()).resolve()
    for d in (here, *here.parents):
        if (d / "conf" / f"{CONFIG_NAME}.yaml").is_file():
            return d / "conf"
    raise ConfigError(f"no conf/{CONFIG_NAME}.yaml in {here} or its parents (run from the project folder)")


def compose(overrides: Sequence[str] = (), conf_dir: str | os.PathLike | None = None) -> DictConfig:
    """Compose ``conf/`` with Hydra override strings; interpolations resolved."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    conf = Path(conf_dir) if conf_dir else find_conf_dir()
    try:
        with initialize_config_dir(config_dir=str(conf.resolve()), version_base=None):
            cfg = hydra_compose(config_name=CONFIG_NAME, overrides=list(overrides))
        OmegaConf.resolve(cfg)
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(f"cannot compose {conf}: {str(exc).splitlines()[0]}") from exc
    return cfg


def compose_yaml(overrides: Sequence[str] = (), conf_dir: str | os.PathLike | None = None) -> str:
    """The text DVC writes to params.yaml for this composition."""
    return OmegaConf.to_yaml(compose(overrides, conf_dir))


def write_params(path: str | os.PathLike = "params.yaml", overrides: Sequence[str] = (),
                 conf_dir: str | os.PathLike | None = None) -> None:
    """Write the composition to ``path`` atomically (same bytes as ``dvc exp run``)."""
    from ..io.atomic import write_text

    write_text(path, compose_yaml(overrides, conf_dir))


@functools.lru_cache(maxsize=1)
def _yaml_loader():
    """OmegaConf's YAML loader (its float rule, e.g. ``1e-3``; duplicate keys an error; no timestamps) on PyYAML's
    C parser when libyaml is there: ``OmegaConf.load`` parses in pure Python, and every `room stage` call reads the
    composed ``params.yaml``."""
    import yaml
    from omegaconf._utils import get_yaml_loader

    base = get_yaml_loader()
    try:
        from yaml.cyaml import CParser
    except ImportError:                                # PyYAML built without libyaml
        return base

    class CLoader(CParser, base):                      # the C scanner / parser, OmegaConf's resolver / constructor
        def __init__(self, stream) -> None:
            CParser.__init__(self, stream)
            yaml.constructor.SafeConstructor.__init__(self)
            yaml.resolver.Resolver.__init__(self)

    return CLoader


def load_yaml(path: str | os.PathLike) -> DictConfig:
    """``OmegaConf.load(path)`` (the same config; tests/test_config.py), parsed by :func:`_yaml_loader`."""
    import yaml

    with open(path, encoding="utf-8") as fh:
        try:
            obj = yaml.load(fh, Loader=_yaml_loader())
        except yaml.YAMLError as exc:                  # a bad file is one line, not a traceback
            mark = getattr(exc, "problem_mark", None)
            where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
            what = getattr(exc, "problem", None) or str(exc).splitlines()[0]
            raise InputError(f"{path}: not valid YAML{where}: {what}") from None
    if obj is not None and not isinstance(obj, dict):
        raise InputError(f"{path}: expected a mapping of config sections, got {type(obj).__name__}")
    return OmegaConf.create(obj or {})


def load_params(path: str | os.PathLike, overrides: Sequence[str] = ()) -> DictConfig:
    """Load a composed config (``params.yaml``) and apply ``key=value`` dot-list overrides."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"params file not found: {path}")
    cfg = load_yaml(path)
    if overrides:
        bad = [o for o in overrides if "=" not in o]
        if bad:
            raise ConfigError(f"override must be key=value: {bad[0]}")
        cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))
    OmegaConf.resolve(cfg)
    return cfg


def section(cfg: DictConfig, key: str) -> dict:
    """A config section as a plain dict (for the ``Params.from_dict`` of domain modules)."""
    if key not in cfg:
        raise ConfigError(f"config has no section '{key}'")
    return OmegaConf.to_container(cfg[key], resolve=True)  # type: ignore[return-value]


@dataclasses.dataclass(frozen=True)
class PhantomEntry:
    """``phantoms.<patient>``: a phantom patient's entry (conf/patients/*.yaml).

    ``seed``: the seed of its random tree and CT texture and noise.  ``tree``: null for a grown tree, else
    the path of a measured tree's branch table (:mod:`room_pipeline.anatomy.reference_tree`; the seed then
    draws the CT's texture and noise only), whose axes are ``tree_frame`` (RAS or LPS) and whose content is
    pinned by ``tree_sha256`` (required with ``tree``: DVC tracks params, not the file, so a table changed
    in place stops the stage with one line instead of leaving the old outputs cached).
    """

    seed: int = 0
    tree: str | None = None
    tree_frame: str = "RAS"
    tree_sha256: str | None = None

    def __post_init__(self) -> None:
        if self.tree_frame not in ("RAS", "LPS"):
            raise ConfigError(f"tree_frame must be RAS or LPS, got {self.tree_frame!r}")
        if self.tree is not None and not self.tree_sha256:
            raise ConfigError(f"tree_sha256 is required with tree ({self.tree}): the sha256 of the table's bytes")


def phantom_entry(cfg: Mapping[str, Any], patient: str) -> PhantomEntry:
    """The ``phantoms.<patient>`` entry read by :func:`~room_pipeline.config.params.params_from_dict` (a bad key
    or value is one :class:`ConfigError` line); a patient that is no phantom is one too."""
    phantoms = cfg.get("phantoms") or {}
    if patient not in phantoms:
        raise ConfigError(f"'{patient}' is not a phantom patient (phantoms: {', '.join(phantoms) or 'none'})")
    entry = phantoms[patient]
    if isinstance(entry, DictConfig):
        entry = OmegaConf.to_container(entry, resolve=True)
    if entry is not None and not isinstance(entry, Mapping):
        raise ConfigError(f"phantoms.{patient} must be a mapping (seed: N), got {entry!r}")
    try:
        return params_from_dict(PhantomEntry, entry, f"phantoms.{patient}")
    except ConfigError as exc:
        if str(exc).startswith(f"phantoms.{patient}") or str(exc).startswith(f"unknown key 'phantoms.{patient}"):
            raise
        raise ConfigError(f"phantoms.{patient}: {exc}") from None


def patient_entry(cfg: DictConfig, patient: str) -> dict:
    """The ``patients.<id>`` entry, validated: ``kind`` (ct | mask), ``input`` (path), optional ``mask_label`` /
    ``mask_threshold`` (masks only, not both) and ``start_pose`` (path of a 4x4 pose in mm, the route's start)."""
    patients = cfg.get("patients") or {}
    if patient not in patients:
        known = ", ".join(sorted(patients)) or "none"
        raise ConfigError(f"unknown patient '{patient}' (configured: {known})")
    entry = OmegaConf.to_container(patients[patient], resolve=True)
    kind = entry.get("kind")
    if kind not in ("ct", "mask"):
        raise ConfigError(f"patients.{patient}.kind must be 'ct' or 'mask', got {kind!r}")
    if not entry.get("input") or not isinstance(entry.get("input"), str):
        raise ConfigError(f"patients.{patient}.input must be a path, got {entry.get('input')!r}")
    for key in ("mask_label", "mask_threshold"):
        v = entry.get(key)
        if v is None:
            continue
        if kind != "mask":
            raise ConfigError(f"patients.{patient}.{key} applies to kind: mask only")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v != v:
            raise ConfigError(f"patients.{patient}.{key} must be a number, got {v!r}")
    if entry.get("mask_label") is not None and entry.get("mask_threshold") is not None:
        raise ConfigError(f"patients.{patient}: give mask_label or mask_threshold, not both")
    start = entry.get("start_pose")
    if start is not None and (not isinstance(start, str) or not start):
        raise ConfigError(f"patients.{patient}.start_pose must be a path (a Med-MPD start*.txt), got {start!r}")
    return entry  # type: ignore[return-value]
