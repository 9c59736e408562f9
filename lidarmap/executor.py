"""Where the per-tile and per-building tasks run: this process, a local dask cluster, or a remote dask scheduler.

``lidarmap run`` and ``lidarmap map update`` describe their work as independent tasks (a pure function of a
payload) and hand them to :func:`map_tasks`, which runs them

- in this process when ``workers == 1`` and no scheduler is given (nothing of dask is imported);
- on a ``dask.distributed.LocalCluster`` of ``workers`` processes (one thread each) started for the call;
- on the cluster behind ``scheduler`` (``tcp://host:8786``), started by the user with ``dask scheduler`` and
  ``dask worker`` (docs/cluster.md).

The caller stays the only writer: results come back to it and it writes them (output folders, the map
transaction). Payloads travel with the tasks, so workers need no access to this machine's files.

Failures: a worker that dies mid-task has its task rescheduled on another worker by the scheduler (dask's
``distributed.scheduler.allowed-failures``, default 3). A task whose function raises is not retried (the same data
fails the same way): the wrapper turns the exception into a :class:`TaskFailure` that the caller reports, and the
other tasks go on. Only ``max_in_flight`` tasks are submitted at a time, so the caller's memory stays bounded by
that many payloads and results whatever the number of tasks.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import uuid
import warnings
import zlib
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from lidarmap.errors import ConfigError, LidarmapError

log = logging.getLogger(__name__)

__all__ = ["TaskFailure", "run_task", "map_tasks", "cluster_client", "check_cluster_params", "derive_seed"]

#: Seconds to wait for a remote scheduler before giving up with a one-line error.
CONNECT_TIMEOUT_S = 20
#: Seconds to wait for a reachable scheduler to have at least one worker (workers may still be starting).
WORKERS_TIMEOUT_S = 120


@dataclasses.dataclass(frozen=True)
class TaskFailure:
    """Why one task produced no result (one line)."""

    reason: str


def run_task(fn: Callable[..., Any], payload: Any, *shared: Any) -> Any:
    """``fn(payload, *shared)``, or a :class:`TaskFailure` carrying the error: bad data in one building must not
    stop a city. Our own errors keep their one-line message; anything else is named by its type."""
    try:
        return fn(payload, *shared)
    except LidarmapError as exc:
        log.warning("task failed: %s", getattr(exc, "problem", str(exc)))
        return TaskFailure(getattr(exc, "problem", str(exc)))
    except (MemoryError, ValueError, ArithmeticError, IndexError, KeyError, RuntimeError, TypeError,
            AssertionError) as exc:  # a bug or bad data in one task; reported, never silently dropped
        return TaskFailure(f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}")


def check_cluster_params(workers: int, scheduler: str) -> None:
    if workers < 1:
        raise ConfigError("workers must be at least 1")
    if scheduler and not scheduler.startswith(("tcp://", "tls://", "inproc://", "ucx://")):
        raise ConfigError(f"scheduler address {scheduler!r} must look like tcp://HOST:PORT")


@contextlib.contextmanager
def cluster_client(workers: int, scheduler: str) -> Iterator[Any]:
    """A dask Client: connected to ``scheduler``, or to a LocalCluster of ``workers`` single-threaded processes."""
    check_cluster_params(workers, scheduler)
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as exc:
            raise ConfigError(f"cannot reach the dask scheduler at {scheduler} ({' '.join(str(exc).split())[:120]})"
                              ) from None
        with client:
            try:  # a scheduler without workers would otherwise accept the tasks and wait forever
                client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
            except (OSError, TimeoutError):
                raise ConfigError(f"the dask scheduler at {scheduler} has no workers (waited {WORKERS_TIMEOUT_S} s); "
                                  f"start some with: dask worker {scheduler}") from None
            yield client
        return
    # one BLAS/torch thread per worker process: workers x threads must not exceed the cores
    env = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    with contextlib.ExitStack() as stack:
        cluster = stack.enter_context(LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                                   dashboard_address=None, silence_logs=logging.ERROR,
                                                   env=env))
        yield stack.enter_context(Client(cluster))


def _identity(obj: Any) -> Any:
    return obj


def _worker_count(client: Any) -> int:
    try:
        return max(1, len(client.scheduler_info().get("workers", {})))
    except (OSError, TimeoutError):
        return 1


def map_tasks(fn: Callable[..., Any], payloads: Iterable[Any], workers: int = 1, scheduler: str = "",
              max_in_flight: int | None = None, client: Any = None, shared: tuple = ()) -> Iterator[tuple[int, Any]]:
    """(number, result) of ``fn(payload, *shared)`` on every payload: results or :class:`TaskFailure`, in
    completion order (in payload order when serial).

    ``payloads`` is consumed lazily (at most ``max_in_flight`` submitted and not yet collected; default twice the
    number of workers, at least 2). ``shared`` objects (a model) are sent to every worker once, not per task.
    ``client`` reuses an open client (see :func:`cluster_client`).
    """
    if client is None and workers == 1 and not scheduler:
        for number, payload in enumerate(payloads):
            yield number, run_task(fn, payload, *shared)
        return
    with contextlib.ExitStack() as stack:
        if client is None:
            client = stack.enter_context(cluster_client(workers, scheduler))
        yield from _map_on(client, fn, payloads, max_in_flight, shared)


def _map_on(client: Any, fn: Callable[..., Any], payloads: Iterable[Any], max_in_flight: int | None,
            shared: tuple) -> Iterator[tuple[int, Any]]:
    from dask.distributed import as_completed
    from distributed.scheduler import KilledWorker

    limit = max_in_flight or max(2, 2 * _worker_count(client))
    # shared objects enter the graph as the result of a task (not scattered): the scheduler keeps the object and
    # recomputes the task on another worker if the one holding its result dies
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ll]arge object.*")
        warnings.filterwarnings("ignore", message=".*[Ss]ending large graph.*")
        shared_data = [client.submit(_identity, obj, pure=False, key=f"shared-{uuid.uuid4().hex[:12]}-{i}")
                       for i, obj in enumerate(shared)]
    numbers: dict[Any, int] = {}
    pending = as_completed()
    source = enumerate(payloads)
    prefix = f"{getattr(fn, '__name__', 'task')}-{uuid.uuid4().hex[:12]}"

    def submit_next() -> bool:
        # the payload travels inside the task (held by the scheduler), not scattered: scattered data dies with the
        # worker holding it, and the task could not be rescheduled
        for number, payload in source:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*[Ll]arge object.*")
                warnings.filterwarnings("ignore", message=".*[Ss]ending large graph.*")
                future = client.submit(run_task, fn, payload, *shared_data, pure=False, key=f"{prefix}-{number}")
            numbers[future] = number
            pending.add(future)
            return True
        return False

    for _ in range(limit):
        if not submit_next():
            break
    for future in pending:
        number = numbers.pop(future)
        try:
            result = future.result()
        except KilledWorker:
            result = TaskFailure("the workers running it died too often (dask allowed-failures); out of memory?")
        except Exception as exc:  # noqa: BLE001 - a task the wrapper could not catch (e.g. unpicklable result)
            result = TaskFailure(f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}")
        future.release()
        yield number, result
        submit_next()


# ----------------------------------------------------------------------------------------------------------------------
# Buildings as tasks: grouping and seeds, shared by the aerial pipeline and the map update


def group_by_cell(boxes: np.ndarray, size: float) -> list[list[int]]:
    """Rows of ``boxes`` (N, 4: xmin, ymin, xmax, ymax) grouped by the ``size`` x ``size`` m cell holding their
    centre (``size`` <= 0: one row per group); groups in the order of their first row, rows in input order.

    Neighbouring buildings share a task so that they share one read of their context (points near several
    buildings are read once per group instead of once per building).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if size <= 0:
        return [[k] for k in range(len(boxes))]
    cells = np.floor((boxes[:, :2] + boxes[:, 2:]) / 2 / size).astype(np.int64)
    groups: dict[tuple[int, int], list[int]] = {}
    for k, key in enumerate(map(tuple, cells.tolist())):
        groups.setdefault(key, []).append(k)
    return list(groups.values())


def building_seed_sequence(seed: int, building_id: str) -> np.random.SeedSequence:
    """The random stream of one building: keyed by (run seed, building id), so it is the same whatever else is in
    the run, however the input is tiled or grouped, serial or on any worker."""
    return np.random.SeedSequence([seed, zlib.crc32(str(building_id).encode("utf-8"))])


def building_seed(seed: int, building_id: str) -> int:
    """A 32-bit integer seed drawn from :func:`building_seed_sequence` (for APIs that take an int)."""
    return int(building_seed_sequence(seed, building_id).generate_state(1)[0])


def derive_seed(seed: int, *keys: int) -> int:
    """A 32-bit integer seed for the sub-step ``keys`` of a task seeded ``seed``: the state of
    ``SeedSequence(seed).spawn(...)``'s child with that spawn key, so sub-steps get independent streams (``seed * 31
    + k`` collides across tasks) and every value fits the ``< 2**32`` seeds scikit-learn takes."""
    sequence = np.random.SeedSequence(int(seed), spawn_key=tuple(int(k) for k in keys))
    return int(sequence.generate_state(1)[0])
