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
"""
from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import math
import multiprocessing
import os
import sys
import pickle
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Protocol, Sequence

from ..config.params import params_from_dict
from ..errors import BackendUnavailable, ConfigError, InputError, RoomError

BACKENDS = ("serial", "local", "ray")

#: ``workers: 0`` (automatic) gives a worker no fewer items than this (frames of a sequence)
MIN_ITEMS_PER_WORKER = 32


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells, else ``os.cpu_count()``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:                             # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


#: ``(factory, args)``: ``factory(*args)`` is each worker's state
Init = tuple[Callable[..., Any], Sequence[Any]]


@dataclasses.dataclass(frozen=True)
class ExecutionParams:
    """Keys of ``conf/execution/default.yaml``.

    backend: 'serial' | 'local' | 'ray'; workers: processes or Ray actors
    (>= 1; 0 = automatic, :meth:`resolved`); ray_address: None for a private local Ray head, else the
    address of a running cluster; chunk_size: items per dispatched chunk (0 = automatic);
    threads_per_worker: library threads per worker (0 = cores // workers, at least 1).
    """

    backend: str = "local"
    workers: int = 0
    ray_address: str | None = None
    chunk_size: int = 0
    threads_per_worker: int = 0

    @property
    def threads(self) -> int:
        """Threads each worker's libraries may use (``threads_per_worker``, or cores // workers)."""
        if self.threads_per_worker > 0:
            return self.threads_per_worker
        return max(1, (os.cpu_count() or 1) // (self.workers or usable_cores()))

    def resolved(self, items: int | None = None) -> "ExecutionParams":
        """These params with ``workers: 0`` (automatic) made a number: one worker per usable core, but no
        more than one per :data:`MIN_ITEMS_PER_WORKER` items (a spawned worker's start-up, ~1.5 s, must be
        small next to its share), at least 1.  Explicit ``workers`` are kept."""
        if self.workers > 0:
            return self
        n = usable_cores()
        if items is not None:
            n = min(n, max(1, int(items) // MIN_ITEMS_PER_WORKER))
        return dataclasses.replace(self, workers=max(1, n))

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(f"execution.backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 0:
            raise ConfigError(f"execution.workers must be >= 1 (or 0 = automatic), got {self.workers}")
        if self.threads_per_worker < 0:
            raise ConfigError(f"execution.threads_per_worker must be >= 0 (0 = automatic), got "
                              f"{self.threads_per_worker}")
        if self.chunk_size < 0:
            raise ConfigError(f"execution.chunk_size must be >= 0 (0 = automatic), got {self.chunk_size}")
        if self.ray_address is not None and (not isinstance(self.ray_address, str) or not self.ray_address):
            raise ConfigError(f"execution.ray_address must be null or a non-empty string, got {self.ray_address!r}")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "ExecutionParams":
        return params_from_dict(cls, d, "execution")


class Executor(Protocol):
    """What every backend offers."""

    backend: str
    workers: int

    def map(self, fn: Callable[[Any, Any], Any], items: Iterable[Any], *, desc: str = "") -> list:
        """``[fn(state, x) for x in items]`` computed by the workers, in input order."""
        ...

    def close(self) -> None:
        """Release the workers (and a Ray head this executor started)."""
        ...


def chunks(n: int, workers: int, chunk_size: int = 0) -> list[range]:
    """Contiguous index ranges covering ``range(n)``: ``chunk_size`` each, or about four per worker when 0."""
    if n <= 0:
        return []
    size = chunk_size if chunk_size > 0 else max(1, math.ceil(n / (4 * max(1, workers))))
    return [range(s, min(s + size, n)) for s in range(0, n, size)]


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


class _Base:
    backend = ""

    def __init__(self, params: ExecutionParams, init: Init | None) -> None:
        self.params = params
        self.workers = params.workers
        self.threads = params.threads
        self.init = init

    def __enter__(self):
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:  # pragma: no cover - overridden
        pass

    def _progress(self, total: int, desc: str):
        from tqdm import tqdm

        from ..progress import enabled

        # a bar only on an interactive terminal outside CI (ROOM_PROGRESS=0/1 overrides): nothing in logs
        return tqdm(total=total, desc=desc or self.backend, unit="item", disable=not enabled(), leave=False,
                    file=sys.stderr)


def _build_state(init: Init | None) -> Any:
    if init is None:
        return None
    factory, args = init
    return factory(*args)


_THREADS: int | None = None
_LIMITER: Any = None


def worker_threads() -> int | None:
    """The thread budget of this worker process (None outside a local / Ray worker)."""
    return _THREADS


def limit_threads(n: int) -> None:
    """Limit the thread pools of the libraries loaded in this process to ``n`` (see the module docstring).

    Called in each worker before and after its state is built, so libraries loaded by the factory are
    limited too; environment variables cover libraries loaded later.
    """
    global _THREADS, _LIMITER
    _THREADS = int(n)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        os.environ[var] = str(n)
    os.environ["OPENIMAGEIO_OPTIONS"] = f"threads={n},exr_threads={n}"
    try:
        from threadpoolctl import threadpool_limits

        _LIMITER = threadpool_limits(limits=n)        # kept: the limit holds while the worker lives
    except ImportError:                                # pragma: no cover - a dependency of the package
        pass
    if "OpenImageIO" in sys.modules:
        oiio = sys.modules["OpenImageIO"]
        oiio.attribute("threads", n)
        oiio.attribute("exr_threads", n)
    if "cv2" in sys.modules:
        sys.modules["cv2"].setNumThreads(n)


def _worker_state(init_bytes: bytes, threads: int, loads: Callable[[bytes], Any] = pickle.loads) -> Any:
    """The worker's state, built after its thread limits are set.

    ``init`` arrives pickled and is unpickled only here, after :func:`limit_threads`: unpickling
    imports the factory's modules (NumPy, Open3D, OpenImageIO, ...), and OpenMP and OpenBLAS size
    their thread pools from the environment when they load.
    """
    limit_threads(threads)
    state = _build_state(loads(init_bytes))
    limit_threads(threads)
    return state


# --------------------------------------------------------------------------- serial


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


# --------------------------------------------------------------------------- Ray


class _RayWorker:
    """The body of one Ray actor: the state built once, then chunks of items."""

    def __init__(self, init: bytes, threads: int) -> None:
        self.error: BaseException | None = None
        try:
            from ray import cloudpickle

            self.state = _worker_state(init, threads, cloudpickle.loads)
        except BaseException as exc:  # noqa: BLE001 - raised with the first chunk, as the original type
            self.state, self.error = None, exc

    def run(self, fn, items: list) -> list:
        if self.error is not None:
            raise self.error
        return [fn(self.state, x) for x in items]

    def pid(self) -> int:
        return os.getpid()


def _import_ray():
    try:
        import ray
    except ImportError:
        raise BackendUnavailable("execution.backend=ray needs the 'ray' package "
                                 "(pip install -c constraints.txt 'ray[default]')") from None
    return ray


class RayExecutor(_Base):
    """One Ray actor per worker, each holding the state; chunks go to whichever actor is free.

    Joins a Ray session already initialised in this process (and leaves it
    running on close); otherwise starts one -- a private head on 127.0.0.1
    with ``num_cpus = workers`` when ``ray_address`` is null, or a connection
    to that cluster -- and shuts it down on close.
    """

    backend = "ray"
    IN_FLIGHT = 2  # chunks queued per actor: the next one is ready when the current one ends

    def __init__(self, params: ExecutionParams, init: Init | None) -> None:
        super().__init__(params, init)
        self.ray = _import_ray()
        self._owns_ray = False
        self._actors: list = []

    def _ensure_actors(self) -> list:
        ray = self.ray
        if not ray.is_initialized():
            kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
            address = self.params.ray_address
            try:
                if address is None:   # "local": a new head even when RAY_ADDRESS or a `ray start` node exists
                    ray.init(address="local", num_cpus=self.workers, _node_ip_address="127.0.0.1", **kw)
                else:
                    ray.init(address=address, **kw)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                where = "a local Ray head" if address is None else f"the Ray cluster at {address!r}"
                raise ConfigError(f"execution.backend=ray: cannot start or reach {where}: {_first_line(exc)}") \
                    from None
            self._owns_ray = True
        if not self._actors:
            cls = ray.remote(num_cpus=1)(_RayWorker)
            init = self.ray.cloudpickle.dumps(self.init)      # unpickled in the actor after its thread limits
            self._actors = [cls.remote(init, self.threads) for _ in range(self.workers)]
        return self._actors

    def _raise_from(self, exc: BaseException, desc: str) -> None:
        ray = self.ray
        if isinstance(exc, ray.exceptions.RayTaskError):
            cause = getattr(exc, "cause", None)
            if isinstance(cause, BaseException) and not isinstance(cause, ray.exceptions.RayError):
                raise cause.with_traceback(None) from None
            raise RoomError(f"{desc or 'execution'}: {_first_line(exc)}") from None
        if isinstance(exc, ray.exceptions.RayError):       # an actor died: start afresh on the next map
            self._kill_actors()
            raise RoomError(f"{desc or 'execution'}: a Ray worker failed ({type(exc).__name__}: "
                            f"{_first_line(exc)})") from None
        raise exc

    def map(self, fn, items, *, desc: str = "") -> list:
        items = list(items)
        if not items:
            return []
        ray = self.ray
        actors = self._ensure_actors()
        parts = chunks(len(items), self.workers, self.params.chunk_size)
        fn_ref = ray.put(fn)
        results: list[list | None] = [None] * len(parts)
        todo = list(range(len(parts)))[::-1]
        running: dict = {}                                  # ObjectRef -> (chunk index, actor)

        def submit(actor) -> None:
            k = todo.pop()
            running[actor.run.remote(fn_ref, [items[i] for i in parts[k]])] = (k, actor)

        for _ in range(self.IN_FLIGHT):
            for actor in actors:
                if todo:
                    submit(actor)
        error: BaseException | None = None
        with self._progress(len(items), desc) as bar:
            while running:
                done, _ = ray.wait(list(running), num_returns=1)
                k, actor = running.pop(done[0])
                try:
                    results[k] = ray.get(done[0])
                    bar.update(len(parts[k]))
                except BaseException as exc:  # noqa: BLE001 - first failure wins; running chunks still finish
                    if error is None:
                        error = exc
                        todo.clear()
                if todo:
                    submit(actor)
        if error is not None:
            self._raise_from(error, desc)
        return [y for part in results for y in part]  # type: ignore[union-attr]

    def actor_pids(self) -> list[int]:
        """Process ids of the actors (diagnostics, tests)."""
        return self.ray.get([a.pid.remote() for a in self._ensure_actors()])

    def _kill_actors(self) -> None:
        for a in self._actors:
            try:
                self.ray.kill(a)
            except Exception:  # noqa: BLE001 - the actor or the session may already be gone
                pass
        self._actors = []

    def close(self) -> None:
        ray = self.ray
        self._kill_actors()
        if self._owns_ray and ray.is_initialized():
            ray.shutdown()
        self._owns_ray = False


# --------------------------------------------------------------------------- factory and helpers


def make_executor(params: ExecutionParams | Mapping[str, Any] | None = None, init: Init | None = None) -> Executor:
    """The executor of ``params.backend``; ``init = (factory, args)`` builds each worker's state once."""
    if not isinstance(params, ExecutionParams):
        params = ExecutionParams.from_dict(params)
    params = params.resolved()                         # workers 0: one per usable core
    if init is not None and (len(init) != 2 or not callable(init[0])):
        raise TypeError("init must be (factory, args) with factory callable")
    cls = {"serial": SerialExecutor, "local": LocalExecutor, "ray": RayExecutor}[params.backend]
    return cls(params, init)


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
