"""The parent's side of ``bench.federation``: spawn nodes, talk to them, always end them.

A `Node` is one spawned process running ``bench._fed_node.node_main``; `cluster` starts an
exporter and ``n`` receivers wired over zenoh on loopback, agrees the sessions, starts the
exports, waits until every receiver's imported stream exists and is subscribed, and on
the way out thaws (SIGCONT) and stops every node, killing what does not stop in time.
Every wait is bounded; a node that fails or dies raises `NodeFailed` with its traceback.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import queue
import signal
import time
from collections.abc import Iterator
from typing import Any

from nacl.signing import SigningKey

from agents.transports import free_tcp_port
from bench import progress
from bench._fed_node import node_main

_CTX = mp.get_context("spawn")  # never fork: a zenoh session may be open in this process


class NodeFailed(RuntimeError):
    """A node died, reported an error, or did not answer in time."""


class Node:
    """One spawned node process: commands in, replies out, SIGSTOP/SIGCONT, always ended."""

    def __init__(self, role: str, name: str, spec: dict[str, Any]) -> None:
        self.role = role
        self.name = name
        self.cmds: Any = _CTX.Queue()
        self.replies: Any = _CTX.Queue()
        self.proc = _CTX.Process(
            target=node_main,
            args=(role, name, spec, self.cmds, self.replies),
            name=f"bench-{name}",
            daemon=True,
        )
        self.frozen = False
        self._next_id = 1
        self._stash: dict[int, tuple[str, Any]] = {}

    def start(self) -> Node:
        """Spawn the process."""
        self.proc.start()
        return self

    @property
    def pid(self) -> int:
        """The process id (NodeFailed before it is started)."""
        if self.proc.pid is None:
            raise NodeFailed(f"{self.name} is not started")
        return self.proc.pid

    def send(self, op: str, *args: Any) -> int:
        """Ask the node to run ``op(*args)``; the id to wait for with `result`."""
        if self.frozen:
            raise NodeFailed(f"{self.name} is frozen (SIGSTOP): it cannot answer {op!r}")
        cid = self._next_id
        self._next_id += 1
        self.cmds.put((cid, op, args))
        return cid

    def result(self, cid: int, timeout: float) -> Any:
        """What command ``cid`` returned; NodeFailed on its error, the node's death or timeout."""
        deadline = time.monotonic() + timeout
        while cid not in self._stash:
            try:
                got, status, data = self.replies.get(timeout=0.1)
            except queue.Empty:
                if not self.proc.is_alive():
                    raise NodeFailed(
                        f"{self.name} exited with code {self.proc.exitcode}{self._last_error()}"
                    ) from None
                if time.monotonic() > deadline:
                    raise NodeFailed(f"{self.name} did not answer within {timeout:g} s") from None
                continue
            if got == 0 and status == "error":
                raise NodeFailed(f"{self.name} failed:\n{data}")
            self._stash[got] = (status, data)
        status, data = self._stash.pop(cid)
        if status == "error":
            raise NodeFailed(f"{self.name}: command {cid} failed:\n{data}")
        return data

    def _last_error(self) -> str:
        with contextlib.suppress(queue.Empty, OSError, ValueError):
            while True:
                _, status, data = self.replies.get_nowait()
                if status == "error":
                    return f":\n{data}"
        return ""

    def call(self, op: str, *args: Any, timeout: float = 10.0) -> Any:
        """Run ``op(*args)`` on the node and return its result (bounded by ``timeout``)."""
        return self.result(self.send(op, *args), timeout)

    def freeze(self) -> None:
        """SIGSTOP the process."""
        os.kill(self.pid, signal.SIGSTOP)
        self.frozen = True

    def thaw(self) -> None:
        """SIGCONT the process."""
        if self.proc.pid is not None and self.proc.is_alive():
            os.kill(self.pid, signal.SIGCONT)
        self.frozen = False

    def ask_stop(self) -> None:
        """Thaw if frozen, then ask the node to stop (it closes its zenoh session)."""
        if self.frozen:
            self.thaw()
        if self.proc.pid is not None and self.proc.is_alive():
            with contextlib.suppress(OSError, ValueError):
                self.cmds.put((0, "stop", ()))

    def end(self, grace: float) -> None:
        """Wait up to ``grace`` s for the process to exit, then kill it; release the queues."""
        if self.proc.pid is not None:
            self.proc.join(max(grace, 0.0))
            if self.proc.is_alive():
                progress(f"{self.name} did not stop in time: killing it")
                self.proc.kill()
                self.proc.join(5)
        for q in (self.cmds, self.replies):
            q.cancel_join_thread()
            q.close()


def _stop_all(nodes: list[Node], grace: float = 15.0) -> None:
    """Thaw and stop every node at once, then end each within a shared deadline."""
    for node in nodes:
        node.ask_stop()
    deadline = time.monotonic() + grace
    for node in nodes:
        node.end(deadline - time.monotonic())


@contextlib.contextmanager
def cluster(
    n_receivers: int, *, start_timeout: float = 60.0, encrypt: bool = True
) -> Iterator[tuple[Node, list[Node]]]:
    """An exporter and ``n_receivers`` receivers over zenoh (peer, loopback), exports flowing.

    ``encrypt``: the sessions' policy (ChaCha20-Poly1305 batches, the platforms' default;
    False: MAC only).
    """
    names = ["exporter"] + [f"receiver-{i}" for i in range(n_receivers)]
    seeds = {n: os.urandom(32) for n in names}
    trust = {n: bytes(SigningKey(s).verify_key) for n, s in seeds.items()}
    port = free_tcp_port()
    exporter = Node(
        "exporter",
        "exporter",
        {"seed": seeds["exporter"], "trust": trust, "port": port, "encrypt": encrypt},
    )
    receivers = [
        Node(
            "receiver",
            n,
            {
                "seed": seeds[n],
                "trust": trust,
                "port": free_tcp_port(),
                "connect": [port],
                "exporter": "exporter",
                "encrypt": encrypt,
            },
        )
        for n in names[1:]
    ]
    nodes = [exporter, *receivers]
    try:
        exporter.start()
        exporter.result(0, start_timeout)  # listening before the receivers connect
        for node in receivers:
            node.start()
        for node in receivers:
            node.result(0, start_timeout)
        progress(f"{len(nodes)} nodes up; agreeing sessions and starting the exports")
        sids = exporter.call(
            "export", [r.name for r in receivers], 10.0, timeout=15 + 12 * len(receivers)
        )
        progress(f"sessions agreed over zenoh: {', '.join(f'{k}={v}' for k, v in sids.items())}")
        deadline = time.monotonic() + 20
        while True:
            exporter.call("push", 16)
            if all(node.call("ready") for node in receivers) and set(exporter.call("acked")) >= {
                r.name for r in receivers
            }:
                break
            if time.monotonic() > deadline:
                raise NodeFailed(
                    "within 20 s, the receivers' imported streams did not all appear, or their "
                    f"acknowledgements did not all reach the exporter ({exporter.call('acked')})"
                )
            time.sleep(0.05)
        yield exporter, receivers
    finally:
        _stop_all(nodes)
