"""A benchmark's child process: spawned, watched, always ended; reports through a queue."""

from __future__ import annotations

import multiprocessing as mp
import queue
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

_CTX = mp.get_context("spawn")  # never fork: a zenoh session may be open in this process


class ChildFailed(RuntimeError):
    """A child process died, reported an error, or did not report in time."""


class Child:
    """One spawned process running ``target(*args, reports, stop)``; a context manager.

    The target puts ``(kind, pid, data)`` tuples on ``reports`` (``"ready"``, ``"error"`` with
    a traceback …) and returns once ``stop`` is set. Leaving the block (or `close`) sets
    ``stop``, waits a little, then kills: no child outlives its benchmark.
    """

    def __init__(
        self,
        target: Callable[..., None],
        args: tuple[Any, ...],
        name: str,
        *,
        path: Sequence[str] = (),
    ) -> None:
        self.name = name
        self.path = list(path)  # put first on the child's module search path
        self.reports: Any = _CTX.Queue()
        self.stop: Any = _CTX.Event()
        self.proc = _CTX.Process(
            target=target, args=(*args, self.reports, self.stop), name=name, daemon=True
        )
        self.started = 0.0  # perf_counter just before the spawn
        self.started_wall = 0.0  # time.time() just before the spawn

    def start(self) -> Child:
        """Spawn the process (the clocks start just before).

        A spawned child takes this process's ``sys.path`` as it is at the spawn: ``path``
        goes first on it for that moment only (what this process imported stays as it is).
        """
        saved = sys.path[:]
        sys.path[:0] = self.path
        try:
            self.started_wall = time.time()
            self.started = time.perf_counter()
            self.proc.start()
        finally:
            sys.path[:] = saved
        return self

    @property
    def pid(self) -> int:
        """The child's process id (ChildFailed before it is started)."""
        if self.proc.pid is None:
            raise ChildFailed(f"{self.name} is not started")
        return self.proc.pid

    def check(self) -> None:
        """ChildFailed when the child has exited (with what it reported, if anything)."""
        if not self.proc.is_alive():
            detail = ""
            try:
                while True:
                    kind, _, data = self.reports.get_nowait()
                    if kind == "error":
                        detail = f":\n{data}"
            except queue.Empty:
                pass
            raise ChildFailed(f"{self.name} exited with code {self.proc.exitcode}{detail}")

    def wait_report(self, kind: str, timeout: float) -> Any:
        """Block until the child reports ``kind``; its data. ChildFailed on error or timeout."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                got, _, data = self.reports.get(timeout=0.1)
            except queue.Empty:
                self.check()
                if time.monotonic() > deadline:
                    raise ChildFailed(
                        f"{self.name} did not report {kind!r} within {timeout:g} s"
                    ) from None
                continue
            if got == "error":
                raise ChildFailed(f"{self.name} failed:\n{data}")
            if got == kind:
                return data

    def rss_mb(self) -> float:
        """The child's resident set size now (VmRSS from /proc), in MB (2**20 bytes)."""
        with open(f"/proc/{self.pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
        raise ChildFailed(f"no VmRSS for {self.name} (pid {self.pid})")

    def close(self, grace: float = 10.0) -> None:
        """Ask the child to stop, wait up to ``grace`` s, then kill it."""
        self.stop.set()
        if self.proc.pid is not None:
            self.proc.join(grace)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join(5)
        self.reports.close()
        self.reports.join_thread()

    def __enter__(self) -> Child:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
