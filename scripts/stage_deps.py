#!/usr/bin/env python3
"""Print the code dependencies of a pipeline stage (for dvc.yaml `deps`).

A stage's code is the import closure, inside ``src/room_pipeline``, of the CLI
(which dispatches) and of ``stages/<name>.py``, including imports made inside
functions, except the bodies of :data:`CLI_RUN_ONLY` (``room run``'s runner: it starts ``room stage`` in
subprocesses, so its imports, e.g. the manifest writer, are no code of a stage).  dvc.yaml lists it package by
package (:func:`package_deps`).  Usage:
``python scripts/stage_deps.py segment``.  The test suite checks that every stage in dvc.yaml lists
exactly this set, and that it covers every module Python really imports for the stage.
"""
from __future__ import annotations

import ast
import functools
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
PKG = "room_pipeline"
#: functions of ``room_pipeline/cli.py`` that ``room stage`` never calls (the `room run` / multirun runner)
CLI_RUN_ONLY = frozenset({"run_pipeline", "multirun"})


def _module_file(mod: str) -> Path | None:
    base = SRC / Path(*mod.split("."))
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    if base.with_suffix(".py").is_file():
        return base.with_suffix(".py")
    return None


def _imports(mod: str, path: Path) -> set[str]:
    """The ``room_pipeline`` modules that the file ``path`` of module ``mod`` imports (statements only)."""
    return set(_imports_of(mod, path.name == "__init__.py", path.read_text(encoding="utf-8")))


@functools.lru_cache(maxsize=None)
def _imports_of(mod: str, is_pkg: bool, text: str) -> frozenset[str]:
    # keyed by the file's text, so a process that asks for several stages (write_dvc_yaml, the tests) parses
    # each module once, and an edited file is parsed again
    package = mod if is_pkg else mod.rpartition(".")[0]
    found: set[str] = set()
    tree = ast.parse(text)
    skip = {id(n) for f in tree.body if mod == f"{PKG}.cli" and isinstance(f, ast.FunctionDef)
            and f.name in CLI_RUN_ONLY for n in ast.walk(f)}
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.split(".")[0] == PKG)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            if target.split(".")[0] != PKG:
                continue
            found.add(target)
            for a in node.names:  # `from . import stages` may name a submodule
                if _module_file(f"{target}.{a.name}"):
                    found.add(f"{target}.{a.name}")
    return frozenset(found)


def closure(*modules: str) -> set[Path]:
    todo, seen = list(modules), set()
    while todo:
        mod = todo.pop()
        parts = mod.split(".")
        for i in range(1, len(parts) + 1):  # parent packages are imported too
            m = ".".join(parts[:i])
            if m in seen:
                continue
            f = _module_file(m)
            if f is None:
                continue
            seen.add(m)
            todo.extend(_imports(m, f))
    return {_module_file(m).relative_to(ROOT) for m in seen}  # type: ignore[union-attr]


def stage_deps(stage: str) -> list[str]:
    """The files of the stage's import closure (what Python loads for ``room stage NAME``)."""
    return sorted(str(p) for p in closure(f"{PKG}.cli", f"{PKG}.stages.{stage}"))


#: sub-packages listed file by file (the others are listed as whole folders): ``stages`` holds one module
#: per stage, and a stage must not rerun when another stage's module changes
FILE_LEVEL = frozenset({"stages"})


def package_deps(stage: str) -> list[str]:
    """The stage's code deps for dvc.yaml: each sub-package of ``room_pipeline`` its import closure touches,
    as one folder (``src/room_pipeline/anatomy``; DVC hashes a folder as one entry and remembers it in its
    state database, so a no-op ``dvc repro`` stats files instead of hashing them), the top-level modules and
    the :data:`FILE_LEVEL` packages' files one by one.  Coarser than the exact closure: a change anywhere in
    a package reruns every stage that imports any of it."""
    out = set()
    for f in stage_deps(stage):
        parts = Path(f).parts            # ('src', 'room_pipeline', ...)
        if len(parts) > 3 and parts[2] not in FILE_LEVEL:
            out.add(str(Path(*parts[:3])))
        else:
            out.add(f)
    return sorted(out)


if __name__ == "__main__":
    for name in sys.argv[1:]:
        print(f"# {name}")
        for p in package_deps(name):
            print(f"        - {p}")
