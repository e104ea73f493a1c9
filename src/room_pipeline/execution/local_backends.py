"""The ``serial`` backend (in this process) and the ``local`` one (a spawn-started process pool, each
process initialised once) of :mod:`~room_pipeline.execution.executor`."""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import pickle
from typing import Any

from ..errors import RoomError
from .executor_base import ExecutionParams, Init, _Base, _build_state, _first_line, _worker_state, chunks


class SerialExecutor(_Base):
    """Everything in this process; the state is built on first use and kept."""

    backend = "serial"

    def __init__(self, params: ExecutionParams, init: Init | None) -> None:
        super().__init__(params, init)
        self._state: Any = None
        self._ready = False

    def map(self, fn, items, *, desc: str = "") -> list:
        items = list(items)
        if not items:
            return []
        if not self._ready:
            self._state = _build_state(self.init)
            self._ready = True
        out = []
        with self._progress(len(items), desc) as bar:
            for x in items:
                out.append(fn(self._state, x))
                bar.update(1)
        return out

    def close(self) -> None:
        self._state, self._ready = None, False


# --------------------------------------------------------------------------- local processes

_WORKER_STATE: Any = None
_WORKER_ERROR: BaseException | None = None


def _local_init(init: bytes, threads: int) -> None:
    """Process-pool initializer: build this process's state once (errors are kept and raised per chunk)."""
    global _WORKER_STATE, _WORKER_ERROR
    try:
        _WORKER_STATE = _worker_state(init, threads)
    except BaseException as exc:  # noqa: BLE001 - re-raised in the parent as the original exception
        _WORKER_ERROR = exc


def _local_chunk(fn, items: list) -> list:
    if _WORKER_ERROR is not None:
        raise _WORKER_ERROR
    return [fn(_WORKER_STATE, x) for x in items]


class LocalExecutor(_Base):
    """A pool of spawned processes, each initialised once with ``init``; the pool lives until :meth:`close`."""

    backend = "local"

    def __init__(self, params: ExecutionParams, init: Init | None) -> None:
        super().__init__(params, init)
        self._pool: cf.ProcessPoolExecutor | None = None

    def _ensure_pool(self) -> cf.ProcessPoolExecutor:
        if self._pool is None:
            try:
                init = pickle.dumps(self.init)
            except Exception as exc:
                raise TypeError(f"execution.backend=local: the worker initializer cannot be sent to a process "
                                  f"({_first_line(exc)}); use module-level functions and picklable arguments") \
                    from None
            self._pool = cf.ProcessPoolExecutor(max_workers=self.workers,
                                                mp_context=multiprocessing.get_context("spawn"),
                                                initializer=_local_init, initargs=(init, self.threads))
        return self._pool

    def map(self, fn, items, *, desc: str = "") -> list:
        items = list(items)
        if not items:
            return []
        try:
            pickle.dumps(fn)
        except Exception as exc:
            raise TypeError(f"execution.backend=local: {getattr(fn, '__name__', fn)!r} cannot be sent to a "
                              f"worker process ({_first_line(exc)}); use a module-level function") from None
        pool = self._ensure_pool()
        parts = chunks(len(items), self.workers, self.params.chunk_size)
        results: list[list | None] = [None] * len(parts)
        futures = {pool.submit(_local_chunk, fn, [items[i] for i in r]): k for k, r in enumerate(parts)}
        error: BaseException | None = None
        with self._progress(len(items), desc) as bar:
            for fut in cf.as_completed(futures):
                k = futures[fut]
                try:
                    results[k] = fut.result()
                    bar.update(len(parts[k]))
                except BaseException as exc:  # noqa: BLE001 - first failure wins, re-raised below
                    if error is None:
                        error = exc
                        for f in futures:
                            f.cancel()                 # queued chunks never start; running ones finish
        if error is not None:
            if isinstance(error, cf.process.BrokenProcessPool):
                if self._pool is not None:
                    self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None
                raise RoomError(f"{desc or 'execution'}: a worker process of the local executor died "
                                f"(killed, or out of memory?)") from error
            if isinstance(error, cf.CancelledError):  # pragma: no cover - only cancelled chunks fail
                raise RoomError(f"{desc or 'execution'}: cancelled") from error
            raise error
        return [y for part in results for y in part]  # type: ignore[union-attr]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
