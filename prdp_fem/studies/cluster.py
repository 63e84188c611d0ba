"""A study's configurations as tasks on a Dask cluster (``dask.distributed``).

Each configuration runs as one task (:func:`run_remote`, in a worker process) that builds its
own problem, runs in a scratch directory and hands back its records and the files it wrote.
The study's process alone writes the output directory: it appends a task's records to
``results.jsonl`` (append-only, fsynced, as a serial study does) and writes its files
atomically when the task has finished, then its ``done`` record. A worker that dies
mid-task leaves nothing behind; the scheduler runs the task again on another worker
(``distributed.scheduler.allowed-failures`` times), so no record is lost or written twice.
``--resume``, a stop and the summary behave as in a serial study: configurations finish in
any order, each with its whole records.

Dask is optional (``pip install -e '.[cluster]'``): nothing here imports it at module level.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from .._atomic import atomic_path
from ..errors import PrdpFemError

__all__ = ["ClusterError", "check_installed", "cluster_client", "executor_client",
           "parse_executor", "run_tasks"]

#: how to install the optional dependency, in every message that needs it
INSTALL_HINT = "pip install -e '.[cluster]' (dask.distributed)"


class ClusterError(PrdpFemError):
    """An executor that cannot run: Dask missing, a bad address, a task whose workers died."""


def parse_executor(spec: str) -> tuple[str, str | None]:
    """``"serial"``, ``"dask"`` or ``"dask=ADDRESS"`` as ``(kind, address)``.

    >>> parse_executor("dask=tcp://10.0.0.1:8786")
    ('dask', 'tcp://10.0.0.1:8786')
    >>> parse_executor("serial")
    ('serial', None)
    """
    kind, _, address = spec.partition("=")
    if kind == "serial" and not address:
        return "serial", None
    if kind == "dask" and (address or "=" not in spec):
        return "dask", address or None
    raise ClusterError(f"--executor {spec!r}: expected 'serial', 'dask' (a local cluster) or "
                       "'dask=ADDRESS' (a running scheduler, e.g. tcp://host:8786)")


def _distributed():
    try:
        import distributed
    except ImportError:
        raise ClusterError(f"--executor dask needs Dask's distributed scheduler: "
                           f"{INSTALL_HINT}") from None
    return distributed


def check_installed() -> None:
    """A :class:`ClusterError` with the install command when Dask's distributed scheduler is
    missing."""
    _distributed()


def executor_client(spec: str) -> contextlib.AbstractContextManager:
    """The ``--executor`` option as a context manager to enter around the study: it yields
    ``None`` (``"serial"``) or a client (:func:`cluster_client`). The option and the Dask
    install are checked now, before anything is named or made; the cluster starts when the
    block is entered."""
    kind, address = parse_executor(spec)
    if kind == "serial":
        return contextlib.nullcontext()
    check_installed()
    return cluster_client(address)


@contextmanager
def cluster_client(address: str | None, *, n_workers: int | None = None,
                   timeout: str = "20s") -> Iterator[Any]:
    """A ``dask.distributed.Client``: on a ``LocalCluster`` of ``n_workers`` single-threaded
    worker processes (default: one per core) when ``address`` is ``None``, else connected to
    the scheduler at ``address`` (waiting up to ``timeout`` for it). Closed (and the local
    cluster shut down) on exit."""
    distributed = _distributed()
    if address is None:
        workers = n_workers or os.cpu_count() or 1
        with distributed.LocalCluster(n_workers=workers, threads_per_worker=1,
                                      processes=True, dashboard_address=None) as cluster, \
                distributed.Client(cluster) as client:
            yield client
        return
    try:
        client = distributed.Client(address, timeout=timeout)
    except OSError as error:
        raise ClusterError(f"--executor dask={address}: no scheduler reached there "
                           f"({error})") from None
    with client:
        yield client


def run_tasks(client, task: Callable, items: list[tuple], finished: Callable) -> None:
    """Submit ``task(*item)`` for every item at once and call ``finished(item, result)`` in
    this process as each completes (in completion order). On an error, a task whose workers
    kept dying, or an interrupt, the tasks still queued or running are cancelled; what
    ``finished`` has written stays."""
    distributed = _distributed()
    tag = uuid.uuid4().hex[:8]  # keys unique per study: a shared scheduler keeps others'
    futures = {client.submit(task, *item, key=f"prdp-fem-{tag}-{index}", pure=False): item
               for index, item in enumerate(items)}
    try:
        for future in distributed.as_completed(list(futures)):
            try:
                result = future.result()
            except distributed.KilledWorker as error:
                raise ClusterError(f"{futures[future][1]!r}: its worker died every time the "
                                   f"task ran ({error}); the finished configurations are "
                                   "kept") from None
            finished(futures[future], result)
    finally:
        pending = [future for future in futures if not future.done()]
        if pending:
            client.cancel(pending)


def collected_files(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory``, by its path relative to it (POSIX separators)."""
    return {path.relative_to(directory).as_posix(): path.read_bytes()
            for path in sorted(directory.rglob("*")) if path.is_file()}


def write_files(out: Path, files: dict[str, bytes]) -> None:
    """Write ``files`` (relative path -> bytes) under ``out``, each atomically
    (:func:`~prdp_fem._atomic.atomic_path`)."""
    for relative, data in files.items():
        path = out / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
