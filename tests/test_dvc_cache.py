"""DVC links stage outputs into its cache instead of copying them (issue #14: bytes on disk).

DVC 3 hardlinks a stage's outputs into ``.dvc/cache`` on commit only when ``hardlink`` is the *first*
``cache.type`` (``dvc/output.py``: ``next(iter(cache_types)) == "hardlink"``); with ``reflink`` first on a
filesystem without reflinks it copied every rendered frame (the default run used 15.4 GB for a 7.8 GB
dataset). This runs a small DVC project with this repository's ``.dvc/config`` and checks that each output
file is the same inode as its cache object, so the dataset is on disk once.
"""
from __future__ import annotations

import configparser
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DVC = Path(sys.executable).with_name("dvc")


def _cache_types() -> list[str]:
    cp = configparser.ConfigParser()
    cp.read(REPO / ".dvc" / "config")
    return [t.strip() for t in cp["cache"]["type"].strip('"').split(",")]


def test_hardlink_is_the_first_cache_type():
    assert _cache_types()[0] == "hardlink", ".dvc/config cache.type must start with hardlink (see module docstring)"


@pytest.mark.skipif(not DVC.exists() or shutil.which("git") is None, reason="needs the dvc and git executables")
def test_stage_outputs_share_inodes_with_the_cache(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("DVC_")}
    run = lambda *a: subprocess.run(a, cwd=tmp_path, env=env, check=True, capture_output=True, text=True)  # noqa: E731
    run("git", "init", "-q")
    run(str(DVC), "init", "-q")
    shutil.copy(REPO / ".dvc" / "config", tmp_path / ".dvc" / "config")
    (tmp_path / "dvc.yaml").write_text(
        "stages:\n  make:\n    cmd: python -c \"import os; os.makedirs('out/frames', exist_ok=True); "
        "[open(f'out/frames/{i}.bin', 'wb').write(os.urandom(4096)) for i in range(5)]\"\n"
        "    outs:\n      - out\n", encoding="utf-8")
    for _ in range(2):                       # a first run and a forced re-run (outputs replaced, not edited)
        run(str(DVC), "repro", "-f", "-q")
        files = sorted((tmp_path / "out").rglob("*.bin"))
        assert len(files) == 5
        cache_inodes = {p.stat().st_ino for p in (tmp_path / ".dvc" / "cache").rglob("*") if p.is_file()}
        for f in files:
            assert f.stat().st_nlink >= 2 and f.stat().st_ino in cache_inodes, f"{f.name} was copied, not linked"
