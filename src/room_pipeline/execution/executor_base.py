"""The executor's configuration (``conf/execution/``), its interface, how items are cut into chunks, and
what each worker does first (build its state, limit its library thread pools); the backends are
:mod:`.local_backends` and :mod:`.ray_backend`, picked by :func:`~room_pipeline.execution.executor.make_executor`."""
from __future__ import annotations

import dataclasses
import math
import os
import pickle
import sys
from typing import Any, Callable, Iterable, Mapping, Protocol, Sequence

from ..config.params import params_from_dict
from ..errors import ConfigError


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
