"""sha256 of a file, or of a folder's files: the one digest of the dataset's records, sequence index and manifest."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of the file at ``path``, or of a folder's files: each file's path relative to the folder
    (POSIX string, UTF-8) then its bytes, files sorted by relative path (a file gives the digest of its bytes)."""
    p = Path(path)
    h = hashlib.sha256()
    files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    for f in files:
        if p.is_dir():
            h.update(str(f.relative_to(p)).encode())
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()
