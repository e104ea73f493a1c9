"""Reproducibility manifest of a dataset folder: every file's sha256, the resolved config, library versions.

``<root>/manifest.json`` (written atomically, deterministic bytes: no time
stamps, sorted keys)::

    {"format": "room-manifest/1",
     "files": [{"path": "patient_000/sequence_000/rgb/frame_0000.png", "sha256": "...", "size": 189529}, ...],
     "config": {... the resolved config ...},
     "versions": {"python": "3.11.x", "numpy": "1.26.4", "bpy": "5.0.1", ..., "torch": null},
     "platform": {"system": "Linux", "machine": "x86_64", ...},
     "extra": {...}}

Paths are relative POSIX paths, sorted; the manifest itself is not listed.
Two runs with the same config and seed must give manifests whose ``files``
and ``config`` agree (:func:`compare_manifests`; the ``execution`` section is
ignored by default because the backend and the number of workers must not
change a byte); versions and platform are compared apart
(:func:`compare_versions`), since a library upgrade is a reason for a
difference, not a difference in the data.  :func:`verify_manifest` re-hashes
the folder and reports missing, truncated or altered files.

Versions are read with ``importlib.metadata`` (installed distributions), so
building a manifest never imports bpy, Open3D or torch.
"""
from __future__ import annotations

import fnmatch
import json
import os
import platform
import re
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any, Mapping

from ..catalog import MANIFEST_NAME
from ..errors import InputError
from ..io.atomic import write_json
from ..io.hashing import sha256_file
from ..io.outputs import is_temp

FORMAT = "room-manifest/1"

#: reported name -> installed distribution names tried in turn
LIBRARIES: dict[str, tuple[str, ...]] = {
    "room-pipeline": ("room-pipeline",),
    "numpy": ("numpy",),
    "scipy": ("scipy",),
    "bpy": ("bpy",),
    "pybullet": ("pybullet",),
    "open3d": ("open3d", "open3d-cpu"),
    "pymeshlab": ("pymeshlab",),
    "OpenImageIO": ("OpenImageIO", "openimageio"),
    "opencv": ("opencv-contrib-python-headless", "opencv-python-headless", "opencv-contrib-python",
               "opencv-python"),
    "pycolmap": ("pycolmap",),
    "dvc": ("dvc",),
    "hydra-core": ("hydra-core",),
    "omegaconf": ("omegaconf",),
    "ray": ("ray",),
    "torch": ("torch",),
}

#: temporary files of room_pipeline.io.atomic: ``.<name>.<8 random chars>.tmp<suffix of name>``
_TEMP_RE = re.compile(r"^\.(?P<name>.+)\.[A-Za-z0-9_]{8}\.tmp(?P<suffix>.*)$")


def _files(root: Path) -> list[Path]:
    """Every regular file under ``root`` except ``root/manifest.json``, sorted by relative POSIX path."""
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for name in filenames:
            p = Path(dirpath) / name
            if p.is_file() and p != root / MANIFEST_NAME:
                found.append(p)
    return sorted(found, key=lambda p: p.relative_to(root).as_posix())


def library_versions() -> dict[str, str | None]:
    """Installed versions of the key libraries (None when not installed) and of Python."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name, dists in LIBRARIES.items():
        out[name] = None
        for dist in dists:
            try:
                out[name] = importlib_metadata.version(dist)
                break
            except importlib_metadata.PackageNotFoundError:
                continue
    return out


def platform_info() -> dict[str, str]:
    return {"system": platform.system(), "release": platform.release(), "machine": platform.machine(),
            "python_implementation": platform.python_implementation()}


def build_manifest(root: str | os.PathLike, config: Mapping[str, Any] | None,
                   extra: Mapping[str, Any] | None = None) -> dict:
    """The manifest of the folder ``root`` (see the module docstring); ``config`` is the resolved config dict."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"manifest: {root} is not a folder")
    files = [{"path": p.relative_to(root).as_posix(), "sha256": sha256_file(p), "size": p.stat().st_size}
             for p in _files(root) if not is_temp(p.name)]       # a writer's temporary file is not data
    doc = {"format": FORMAT, "files": files, "config": _plain(config or {}),
           "versions": library_versions(), "platform": platform_info()}
    if extra:
        doc["extra"] = _plain(extra)
    return doc


def write_manifest(root: str | os.PathLike, config: Mapping[str, Any] | None,
                   extra: Mapping[str, Any] | None = None) -> Path:
    """Build the manifest of ``root`` and write it atomically to ``<root>/manifest.json``; returns that path."""
    doc = build_manifest(root, config, extra)
    path = Path(root) / MANIFEST_NAME
    write_json(path, doc)
    return path


def read_manifest(path_or_root: str | os.PathLike) -> dict:
    """A manifest from its file or from the dataset folder holding ``manifest.json``."""
    p = Path(path_or_root)
    if p.is_dir():
        p = p / MANIFEST_NAME
    if not p.is_file():
        raise InputError(f"manifest not found: {p}")
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{p}: not a readable manifest ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or not isinstance(doc.get("files"), list):
        raise InputError(f"{p}: not a {FORMAT} manifest")
    return doc


def _plain(obj: Any) -> Any:
    """JSON-shaped copy: mappings -> dicts (string keys), sequences -> lists, paths -> strings."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "item") and callable(obj.item) and getattr(obj, "shape", None) == ():
        return obj.item()
    try:  # OmegaConf containers without importing omegaconf here
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(obj, (DictConfig, ListConfig)):
            return _plain(OmegaConf.to_container(obj, resolve=True))
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        pass
    return obj


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, Mapping) and d:
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: d}


def compare_manifests(a: Mapping[str, Any], b: Mapping[str, Any],
                      ignore_config: tuple[str, ...] = ("execution",),
                      ignore_files: tuple[str, ...] = ()) -> list[str]:
    """Differences between two manifests' files and configs, one readable line each (empty: identical data).

    Config keys under ``ignore_config`` (dotted prefixes) are skipped: by
    default the ``execution`` section, which must not change the outputs.
    Files matching a glob of ``ignore_files`` (``fnmatch`` on the relative
    path, e.g. ``"*/metrics/*"`` for files holding wall times) are skipped.
    """
    diffs: list[str] = []

    def listed(m: Mapping[str, Any]) -> dict:
        return {f["path"]: f for f in m.get("files", [])
                if not any(fnmatch.fnmatchcase(f["path"], pat) for pat in ignore_files)}

    fa, fb = listed(a), listed(b)
    for p in sorted(set(fa) - set(fb)):
        diffs.append(f"file missing in the second: {p}")
    for p in sorted(set(fb) - set(fa)):
        diffs.append(f"file only in the second: {p}")
    for p in sorted(set(fa) & set(fb)):
        x, y = fa[p], fb[p]
        if x["sha256"] != y["sha256"] or x["size"] != y["size"]:
            diffs.append(f"file differs: {p} (sha256 {x['sha256'][:12]} vs {y['sha256'][:12]}, "
                         f"{x['size']} vs {y['size']} bytes)")

    def keep(key: str) -> bool:
        return not any(key == ig or key.startswith(ig + ".") for ig in ignore_config)

    ca = {k: v for k, v in _flatten(a.get("config", {})).items() if keep(k)}
    cb = {k: v for k, v in _flatten(b.get("config", {})).items() if keep(k)}
    for k in sorted(set(ca) | set(cb)):
        if k not in cb:
            diffs.append(f"config {k}: {ca[k]!r} in the first, absent in the second")
        elif k not in ca:
            diffs.append(f"config {k}: absent in the first, {cb[k]!r} in the second")
        elif ca[k] != cb[k]:
            diffs.append(f"config {k}: {ca[k]!r} vs {cb[k]!r}")
    return diffs


def compare_versions(a: Mapping[str, Any], b: Mapping[str, Any]) -> list[str]:
    """Library-version and platform differences between two manifests, one line each."""
    diffs = []
    for field in ("versions", "platform"):
        va, vb = a.get(field, {}) or {}, b.get(field, {}) or {}
        for k in sorted(set(va) | set(vb)):
            if va.get(k) != vb.get(k):
                diffs.append(f"{field} {k}: {va.get(k)} vs {vb.get(k)}")
    return diffs


def verify_manifest(root: str | os.PathLike, strict: bool = True) -> list[str]:
    """Re-hash ``root`` against its ``manifest.json``: problems, one line each (empty: the folder is intact).

    Reports listed files that are missing, of another size (truncated) or
    another sha256; with ``strict``, also files present but not listed (e.g.
    a writer's leftover temporary file).
    """
    root = Path(root)
    doc = read_manifest(root)
    problems = []
    listed = set()
    for f in doc["files"]:
        rel = f["path"]
        listed.add(rel)
        p = root / rel
        if not p.is_file():
            problems.append(f"missing: {rel}")
            continue
        size = p.stat().st_size
        if size != f["size"]:
            problems.append(f"size differs (truncated?): {rel} ({size} bytes, manifest {f['size']})")
        elif sha256_file(p) != f["sha256"]:
            problems.append(f"content differs: {rel}")
    if strict:
        for p in _files(root):
            rel = p.relative_to(root).as_posix()
            if rel not in listed:
                problems.append(f"not in the manifest: {rel}")
    return problems


def stale_temp_files(root: str | os.PathLike) -> list[Path]:
    """Leftover temporary files of :mod:`room_pipeline.io.atomic` under ``root`` (a writer was killed).

    Matches ``.<name>.<8 chars>.tmp<suffix>`` where ``<suffix>`` is the full
    suffix of ``<name>`` -- the names ``atomic_path`` gives -- and nothing else.
    """
    out = []
    root = Path(root)
    every = [Path(d) / f for d, _, fs in os.walk(root) for f in fs]
    for p in sorted(every):
        m = _TEMP_RE.match(p.name)
        if m and m.group("suffix") == "".join(Path(m.group("name")).suffixes):
            out.append(p)
    return out


def remove_stale_temp_files(root: str | os.PathLike) -> list[Path]:
    """Delete :func:`stale_temp_files` (call before re-running into ``root``, with no writer active there)."""
    removed = []
    for p in stale_temp_files(root):
        try:
            p.unlink()
            removed.append(p)
        except FileNotFoundError:
            pass
    return removed
