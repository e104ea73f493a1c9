"""Parallel execution of independent work items (serial, local processes, Ray) and the dataset manifest.

:mod:`.executor` -- :func:`make_executor` / :class:`ExecutionParams` (config section ``execution``);
:mod:`.manifest` -- ``manifest.json``: file hashes, resolved config, library versions.
"""
from __future__ import annotations

from .executor import (BACKENDS, ExecutionParams, Executor, chunks, ensure_writable, limit_threads, make_executor,
                       params_for_items, worker_threads)
from .manifest import (build_manifest, compare_manifests, compare_versions, read_manifest, remove_stale_temp_files,
                       stale_temp_files, verify_manifest, write_manifest)

__all__ = ["BACKENDS", "ExecutionParams", "Executor", "chunks", "ensure_writable", "limit_threads", "make_executor",
           "params_for_items", "worker_threads",
           "build_manifest", "compare_manifests", "compare_versions", "read_manifest", "remove_stale_temp_files",
           "stale_temp_files", "verify_manifest", "write_manifest"]
