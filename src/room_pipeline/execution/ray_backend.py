"""The ``ray`` backend of :mod:`~room_pipeline.execution.executor`: one Ray actor per worker holding its
state; a private loopback head or an existing cluster (``ray_address``)."""
from __future__ import annotations

import os
from typing import Any

from ..errors import BackendUnavailable, ConfigError, RoomError
from .executor_base import ExecutionParams, Init, _Base, _first_line, _worker_state, chunks


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
