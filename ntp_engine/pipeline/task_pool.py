"""Where independent pieces of work run: in this process, one after the other (``LocalPool``), or
as Ray tasks on a cluster (``RayPool``; ``ntp reconstruct --ray``, ``ntp batch --ray``).

Both run the same function on the same items, so a result never depends on where it was computed.
Ray is imported only when a ``RayPool`` is entered: without ``--ray`` nothing imports it. A task
whose worker dies (a killed process, a lost node) is retried by Ray (``RETRIES``); an exception the
function raises is not retried and comes back as itself. Items travel to the workers through Ray's
object store, the shared arguments once; at most ``IN_FLIGHT_PER_CPU`` tasks per cluster CPU are
submitted at a time, so a large input is never copied into the store all at once.
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Protocol, TypeVar

from ..io.errors import NtpInputError

R = TypeVar("R")
RETRIES = 3  # a task whose worker process dies is run again up to this many times
IN_FLIGHT_PER_CPU = 2  # tasks submitted ahead per CPU: workers never wait, the store stays small
LOCAL = "local"  # --ray without an address: a Ray instance on this machine, for this run
CONNECT_TIMEOUT_S = 5.0  # a cluster address must answer within this


def _check_reachable(address: str) -> None:
    """``NtpInputError`` unless a ``HOST:PORT`` or ``ray://HOST:PORT`` address accepts a TCP
    connection (``local`` and ``auto`` are Ray's own to resolve)."""
    if address in (LOCAL, "auto"):
        return
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit():
        raise NtpInputError(None, f"--ray {address}: expected HOST:PORT, ray://HOST:PORT or auto")
    try:
        socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as err:
        raise NtpInputError(None, f"--ray {address}: cannot reach the Ray cluster ({err.strerror or err})") from None


class TaskPool(Protocol):
    """Runs ``fn(item, *shared)`` for every item; yields ``(index, result)`` as results arrive.
    Entered (``with``) around its use: a Ray pool connects only when there is work."""

    def __enter__(self) -> TaskPool: ...

    def __exit__(self, *exc: object) -> None: ...

    def map(
        self, fn: Callable[..., R], items: Iterable[Any], shared: tuple = (), cpus: int = 1
    ) -> Iterator[tuple[int, R]]:
        """``(index, fn(item, *shared))`` per item; ``cpus``: CPUs each call asks for."""
        ...


class LocalPool:
    """Every item in this process, in order."""

    def __enter__(self) -> LocalPool:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def map(
        self, fn: Callable[..., R], items: Iterable[Any], shared: tuple = (), cpus: int = 1
    ) -> Iterator[tuple[int, R]]:
        """``(index, fn(item, *shared))`` per item, in order (``cpus`` unused: this process)."""
        for i, item in enumerate(items):
            yield i, fn(item, *shared)


class RayPool:
    """Items as Ray tasks, each asking ``cpus`` CPUs. ``address``: ``LOCAL`` starts a Ray instance
    on this machine for the run (``threads`` CPUs, 0: every core); anything else is passed to
    ``ray.init`` (``auto``, ``HOST:6379``, ``ray://HOST:10001``). A process already connected to
    Ray (``ray.init`` before) keeps its connection. Use as a context manager."""

    def __init__(self, address: str = LOCAL, threads: int = 0):
        self.address, self.threads = address, threads
        self._ray: Any = None
        self._owned = False
        _check_reachable(address)  # before any work: ray.init waits for an unreachable host forever

    def __enter__(self) -> RayPool:
        try:
            import ray
        except ImportError:
            raise NtpInputError(None, "--ray: the ray package is not installed (pip install ray)") from None
        self._ray = ray
        if not ray.is_initialized():
            local = self.address == LOCAL
            try:
                ray.init(
                    address=None if local else self.address,
                    num_cpus=(self.threads or None) if local else None,
                    include_dashboard=False,
                    logging_level=logging.WARNING,
                    log_to_driver=False,
                    configure_logging=False,
                )
            except (ConnectionError, ValueError, RuntimeError) as err:
                raise NtpInputError(None, f"--ray {self.address}: cannot connect to a Ray cluster ({err})") from None
            self._owned = True
        return self

    def __exit__(self, *exc: object) -> None:
        if self._owned:
            self._ray.shutdown()

    def map(
        self, fn: Callable[..., R], items: Iterable[Any], shared: tuple = (), cpus: int = 1
    ) -> Iterator[tuple[int, R]]:
        """``(index, fn(item, *shared))`` per item as tasks finish (any order)."""
        ray = self._ray
        task = ray.remote(num_cpus=cpus, max_retries=RETRIES, retry_exceptions=False)(fn)
        refs = [ray.put(s) for s in shared]
        cluster_cpus = int(ray.cluster_resources().get("CPU", 1))
        ahead = max(1, IN_FLIGHT_PER_CPU * cluster_cpus // max(cpus, 1))
        pending: dict[Any, int] = {}
        todo = iter(enumerate(items))
        try:
            while True:
                for i, item in todo:
                    pending[task.remote(item, *refs)] = i
                    if len(pending) >= ahead:
                        break
                if not pending:
                    return
                (ready,), _ = ray.wait(list(pending), num_returns=1)
                i = pending.pop(ready)
                try:
                    result = ray.get(ready)
                except ray.exceptions.RayTaskError as err:  # the function's own exception, as itself
                    raise err.cause from None
                yield i, result
        finally:
            for ref in pending:  # stopped early (an error, Ctrl-C): nothing keeps running for us
                ray.cancel(ref, force=True)
