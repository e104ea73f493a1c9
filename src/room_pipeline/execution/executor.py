"""Run embarrassingly parallel work (frames, sequences, patients) on one of three backends.

Usage::

    params = ExecutionParams.from_dict(section(cfg, "execution"))
    with make_executor(params, init=(build_renderer, (scene_args,))) as ex:
        records = ex.map(render_frames, chunks, desc="render")

``factory(*args)`` builds the per-worker state once per worker (a renderer
with its BVH, a loaded scene, ...); ``fn(state, item)`` does one item's work
and returns a small, picklable result.  ``map`` returns the results in input
order whatever the backend.

Backends
    ``serial``: in this process (tests, debugging, profiling).
    ``local``: ``concurrent.futures.ProcessPoolExecutor`` with the *spawn*
    start method (bpy, Open3D and pybullet are not fork-safe), each process
    initialised once.
    ``ray``: one Ray actor per worker holding the state; ``ray_address``
    null starts a private head on this machine (loopback only, even if
    ``RAY_ADDRESS`` is set), otherwise ``ray.init(address=...)`` joins a
    running cluster (``"auto"``: ``RAY_ADDRESS`` or the node started here by
    ``ray start``; ``"host:6379"``; ``"ray://host:10001"``).

Threads
    Each local or Ray worker limits the thread pools of the libraries it
    loads (BLAS / OpenMP through threadpoolctl, OpenImageIO's EXR codec,
    OpenCV) to ``threads_per_worker`` (0: cores // workers), so workers do not
    compete for the cores each other uses; the work function can read the
    number from :func:`worker_threads` (the render stage gives it to Open3D and
    Cycles).  The serial backend leaves this process's threads alone.

Items are dispatched in contiguous chunks (``chunk_size``; 0 = about four
chunks per worker), so a worker rendering frames in order keeps its cache of
the previous cast.

Errors
    An exception raised by ``factory`` or ``fn`` in a worker is re-raised here
    as the same type with the same message (not a wrapper), after the chunks
    already running have finished: nothing is killed mid-write, so a work
    function that writes atomically leaves no partial file.  A worker process
    that dies (killed, out of memory) raises :class:`RoomError`.  Nothing is
    retried and nothing is swallowed.

Modules: :mod:`.executor_base` (the configuration, the interface, chunking, worker threads),
:mod:`.local_backends` (``serial``, ``local``), :mod:`.ray_backend` (``ray``); this one picks the
backend (:func:`make_executor`) and re-exports their public names.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Mapping

from ..errors import InputError
from .executor_base import ExecutionParams, Executor, Init, _first_line
from .local_backends import LocalExecutor, SerialExecutor
from .ray_backend import RayExecutor

# the executor's API, importable from here as before the split
from .executor_base import (BACKENDS, MIN_ITEMS_PER_WORKER, chunks, limit_threads, usable_cores,  # noqa: F401
                            worker_threads)


def make_executor(params: ExecutionParams | Mapping[str, Any] | None = None, init: Init | None = None) -> Executor:
    """The executor of ``params.backend``; ``init = (factory, args)`` builds each worker's state once."""
    if not isinstance(params, ExecutionParams):
        params = ExecutionParams.from_dict(params)
    params = params.resolved()                         # workers 0: one per usable core
    if init is not None and (len(init) != 2 or not callable(init[0])):
        raise TypeError("init must be (factory, args) with factory callable")
    cls = {"serial": SerialExecutor, "local": LocalExecutor, "ray": RayExecutor}[params.backend]
    return cls(params, init)


def params_for_items(execution: ExecutionParams | Mapping[str, Any] | None, items: int | None = None) -> ExecutionParams:
    """The ``execution`` section for ``items`` independent items: ``workers: 0`` resolved
    (:meth:`ExecutionParams.resolved`), and ``local`` with one worker run in this process (``serial``): a spawned
    process would only add its start-up time, the outputs are the same bytes either way."""
    import dataclasses

    p = execution if isinstance(execution, ExecutionParams) else ExecutionParams.from_dict(execution)
    p = p.resolved(items)
    if p.backend == "local" and p.workers == 1:
        return dataclasses.replace(p, backend="serial")
    return p


def ensure_writable(*folders: str | os.PathLike, need_bytes: int = 0) -> None:
    """Check before any work starts that each folder can take new files (and ``need_bytes`` more in all).

    Creates missing folders, writes and removes one empty temporary file in
    each; raises :class:`InputError` naming the folder and the reason
    (permission, read-only file system, no space) instead of failing half-way.
    """
    for folder in folders:
        d = Path(folder)
        try:
            d.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".room-write-check.", dir=d)
            os.close(fd)
            os.unlink(tmp)
        except OSError as exc:
            raise InputError(f"output folder {d} is not writable: {exc.strerror or _first_line(exc)}") from None
        if need_bytes > 0:
            free = shutil.disk_usage(d).free
            if free < need_bytes:
                raise InputError(f"output folder {d}: {free / 1e6:.0f} MB free, about {need_bytes / 1e6:.0f} MB "
                                 f"needed")
