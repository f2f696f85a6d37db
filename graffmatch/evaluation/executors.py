"""Pluggable execution of independent tasks: serial, a local process pool, Dask or Ray.

A study is tens of thousands of independent (pair, method) tasks. The runner hands an iterable of
tasks to an :class:`Executor` and gets ``(index, result)`` back *as each task completes*, so that
it can persist every result at once: whatever happens to the driver or a worker later, finished
results are on disk and a rerun resumes.

Engines:

* ``serial``: in-process, deterministic order; for debugging and tiny studies.
* ``local`` (default): :class:`concurrent.futures.ProcessPoolExecutor` with N workers.
* ``dask``: Dask distributed. With ``address="tcp://host:8786"`` it connects to an existing
  scheduler (a cluster started with ``dask scheduler`` / ``dask worker`` or dask-jobqueue);
  without an address it starts a :class:`distributed.LocalCluster` of N single-threaded worker
  processes and closes it afterwards. Dask re-runs tasks of a worker that died.
* ``ray``: Ray (``ray.init(address=...)``). Ray is the optional extra ``graffmatch[ray]`` (``make
  test`` installs it); selecting it without Ray raises :class:`ExecutorUnavailableError`
  with the pip command to fix it.

Only a bounded number of tasks is in flight at a time (``max_in_flight``) so that a study of
100k tasks does not pickle every input up front.
"""

from __future__ import annotations

import importlib
import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol, TypeVar

from graffmatch.errors import GraffMatchError, InvalidInputError

T = TypeVar("T")
R = TypeVar("R")

EXECUTOR_NAMES = ("serial", "local", "dask", "ray")


class ExecutorUnavailableError(GraffMatchError):
    """The selected execution engine is not installed or cannot be reached."""


class WorkerLostError(GraffMatchError):
    """A worker died mid-run (killed, out of memory); finished results are kept, rerun to resume."""


class Executor(Protocol):
    """Runs ``fn`` over items and yields ``(index, result)`` in completion order."""

    name: str

    def imap_unordered(
        self, fn: Callable[[T], R], items: Iterable[T]
    ) -> Iterator[tuple[int, R]]: ...

    def close(self) -> None: ...


def default_workers() -> int:
    """Worker count when none is given: all usable cores (at least 1)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def _require(module: str, hint: str) -> Any:
    """Import an optional engine, or say how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ExecutorUnavailableError(hint) from exc


def _window(max_in_flight: int | None, n_workers: int) -> int:
    """Tasks kept in flight: enough to keep every worker busy, few enough to stop quickly."""
    return int(max_in_flight or 4 * n_workers)


class _ClosesOnExit:
    """``with executor:`` closes it (pools, clients, clusters) however the block ends."""

    def close(self) -> None:  # pragma: no cover - every executor overrides it
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SerialExecutor(_ClosesOnExit):
    """In-process execution in input order (exceptions propagate unchanged)."""

    name = "serial"

    def imap_unordered(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[tuple[int, R]]:
        for i, item in enumerate(items):
            yield i, fn(item)

    def close(self) -> None:
        return None


class LocalProcessExecutor(_ClosesOnExit):
    """A local process pool with a bounded submission window."""

    name = "local"

    def __init__(
        self,
        workers: int | None = None,
        max_in_flight: int | None = None,
        start_method: str | None = None,
        preload: Sequence[str] = ("graffmatch.evaluation.runner",),
    ) -> None:
        self.workers = int(workers or default_workers())
        if self.workers < 1:
            raise InvalidInputError(f"workers must be >= 1, got {workers}")
        self.max_in_flight = _window(max_in_flight, self.workers)
        # forkserver, not fork: the driver has threads (progress bar, Dask), and forking a
        # threaded process can deadlock. The server preloads the heavy imports once.
        methods = multiprocessing.get_all_start_methods()
        self.start_method = start_method or ("forkserver" if "forkserver" in methods else "spawn")
        self.preload = list(preload)
        self._pool: ProcessPoolExecutor | None = None

    def _get_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            ctx = multiprocessing.get_context(self.start_method)
            if self.start_method == "forkserver" and self.preload:
                ctx.set_forkserver_preload(self.preload)
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx)
        return self._pool

    def imap_unordered(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[tuple[int, R]]:
        pool = self._get_pool()
        it = enumerate(items)
        pending: dict[Future[R], int] = {}

        def fill() -> None:
            while len(pending) < self.max_in_flight:
                try:
                    i, item = next(it)
                except StopIteration:
                    return
                pending[pool.submit(fn, item)] = i

        try:
            try:
                fill()
                while pending:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        i = pending.pop(fut)
                        result = fut.result()
                        yield i, result
                    fill()
            except BrokenProcessPool as exc:
                raise WorkerLostError(
                    "a worker process died (killed or out of memory); finished results "
                    "are saved, rerun to resume"
                ) from exc
        finally:
            for fut in pending:
                fut.cancel()
            if pending:  # an error or an abandoned generator: do not leave work running
                self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class DaskExecutor(_ClosesOnExit):
    """Dask distributed: an existing scheduler (``address``) or a temporary LocalCluster."""

    name = "dask"

    def __init__(
        self,
        address: str | None = None,
        workers: int | None = None,
        max_in_flight: int | None = None,
        client: Any | None = None,
    ) -> None:
        distributed = _require(
            "distributed",
            "the dask executor needs 'dask[distributed]': pip install 'dask[distributed]'",
        )
        self._cluster = None
        self._own_client = client is None
        if client is not None:
            self.client = client
        elif address:
            try:
                self.client = distributed.Client(address, timeout="20s")
            except OSError as exc:
                raise ExecutorUnavailableError(
                    f"cannot reach the Dask scheduler at {address!r}: {exc}"
                ) from exc
        else:
            n = int(workers or default_workers())
            # One thread per worker process: the tasks are CPU-bound numpy code.
            self._cluster = distributed.LocalCluster(
                n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None
            )
            self.client = distributed.Client(self._cluster)
        n_threads = sum(self.client.nthreads().values()) or 1
        self.max_in_flight = _window(max_in_flight, n_threads)

    def imap_unordered(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[tuple[int, R]]:
        from distributed import as_completed

        it = enumerate(items)
        pending: dict[str, tuple[int, Any]] = {}  # key -> (index, future)
        ac = as_completed(with_results=False)

        def submit_one() -> bool:
            try:
                i, item = next(it)
            except StopIteration:
                return False
            # pure=False: every task runs (no result de-duplication by argument hash).
            fut = self.client.submit(fn, item, pure=False)
            pending[fut.key] = (i, fut)
            ac.add(fut)
            return True

        while len(pending) < self.max_in_flight and submit_one():
            pass
        try:
            for fut in ac:
                i, _ = pending.pop(fut.key)
                result = fut.result()  # re-raises the task's exception (or KilledWorker)
                fut.release()
                yield i, result
                submit_one()
        finally:
            if pending:  # an error or an abandoned generator: stop the remaining tasks
                ac.clear()
                self.client.cancel([f for _, f in pending.values()])

    def close(self) -> None:
        if self._own_client:
            self.client.close()
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None


class RayExecutor(_ClosesOnExit):
    """Ray (the optional extra ``graffmatch[ray]``): ``ray.init(address)`` and ``ray.wait``."""

    name = "ray"

    def __init__(
        self,
        address: str | None = None,
        workers: int | None = None,
        max_in_flight: int | None = None,
    ) -> None:
        ray = _require(
            "ray",
            "the ray executor needs Ray: pip install 'graffmatch[ray]' (or use --executor dask)",
        )
        self._ray = ray
        self._own = not ray.is_initialized()
        if self._own:
            if address:
                ray.init(address=address)
            else:
                ray.init(num_cpus=int(workers or default_workers()))
        n = int(ray.cluster_resources().get("CPU", 1))
        self.max_in_flight = _window(max_in_flight, n)
        self._remote_cache: dict[Callable[..., Any], Any] = {}

    def imap_unordered(self, fn: Callable[[T], R], items: Iterable[T]) -> Iterator[tuple[int, R]]:
        ray = self._ray
        # max_retries: Ray re-runs a task whose worker process died.
        remote = self._remote_cache.setdefault(fn, ray.remote(max_retries=3)(fn))
        it = enumerate(items)
        pending: dict[Any, int] = {}

        def fill() -> None:
            while len(pending) < self.max_in_flight:
                try:
                    i, item = next(it)
                except StopIteration:
                    return
                pending[remote.remote(item)] = i

        fill()
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    i = pending.pop(ref)
                    yield i, ray.get(ref)
                fill()
        finally:
            for ref in pending:
                ray.cancel(ref)

    def close(self) -> None:
        if self._own:
            self._ray.shutdown()


def make_executor(
    name: str = "local",
    workers: int | None = None,
    address: str | None = None,
    max_in_flight: int | None = None,
) -> Executor:
    """Build an executor by name: 'serial', 'local' (default), 'dask' or 'ray'."""
    key = (name or "local").lower()
    if key == "serial":
        return SerialExecutor()
    if key in ("local", "process", "processes"):
        if address:
            raise InvalidInputError("--address is for cluster executors (dask, ray), not 'local'")
        return LocalProcessExecutor(workers=workers, max_in_flight=max_in_flight)
    if key == "dask":
        return DaskExecutor(address=address, workers=workers, max_in_flight=max_in_flight)
    if key == "ray":
        return RayExecutor(address=address, workers=workers, max_in_flight=max_in_flight)
    raise InvalidInputError(f"unknown executor {name!r}; choose one of {', '.join(EXECUTOR_NAMES)}")
