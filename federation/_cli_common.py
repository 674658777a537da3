"""What the ``dyknow`` commands and a running node share: membership views, task failures, GC.

Apart from ``_cli_net`` (the commands) and ``_local`` (the running node's local channel),
which both use these and would otherwise import each other.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import sys
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import TYPE_CHECKING, Any

from agents import Failed, NotUnderstood, Refused, ReplyTimeout, TransportError
from ontology import UnknownSemanticLabel

from ._service_content import ContentError

if TYPE_CHECKING:
    from ._platform import FederationPlatform

__all__ = [
    "NotAnsweredError",
    "WatchLostError",
    "complain",
    "error_text",
    "failure_of",
    "platforms_of",
    "reaching",
    "settle_gc",
    "wait_for_members",
]


def complain(line: str) -> None:
    """Print one line on stderr, flushed (a supervisor may be reading)."""
    print(line, file=sys.stderr, flush=True)


def settle_gc() -> None:
    """Move what start-up allocated out of the cyclic GC's sight (a long-running node).

    The modules, agents and caches built at start-up live as long as the process; without
    this, every full collection walks them again (measured: 16-24% of a node's loop time
    in the GC, a 70 ms pause inside a global query at scale). What was frozen before
    (`dyknow node` freezes its imports, ``federation._cli_node``) is collected with the
    rest, so the garbage among it is freed.
    """
    gc.unfreeze()
    gc.collect()
    gc.freeze()


async def failure_of(job: Callable[..., Awaitable[Any]], *args: Any) -> Exception | None:
    """Run ``job(*args)``; its failure is returned, not raised.

    For the tasks of a task group whose failure the caller raises itself: a group would
    raise it wrapped in an ExceptionGroup, and cancel its siblings and its caller first.
    """
    try:
        await job(*args)
    except Exception as exc:
        return exc
    return None


class NotAnsweredError(Exception):
    """The asked platform did not answer; the message says the likely cause."""


class WatchLostError(TransportError):
    """The owner's watch stopped: the transport ended a subscription of its (exit 1).

    Its message names each one; run again, the watch subscribes anew (or fails to start,
    naming why).
    """


_IN_WORDS = (
    Refused,
    Failed,
    NotUnderstood,
    ReplyTimeout,
    UnknownSemanticLabel,
    ContentError,  # Denied among them
    NotAnsweredError,
    WatchLostError,
)
"""The errors that say what they are in words: their class is not printed."""


def error_text(exc: BaseException) -> str:
    """An error as a command prints it: in its own words when they say what it is.

    A platform's answer that was no (refused, failed, not understood) or none at all, a
    label or a request refused (here or by the platform asked) say it in words
    (``federation@uav-a refused: …``, ``semantic label 'x' has no mapping on this
    platform``): their Python class adds nothing. Another error, an internal state's
    (``ConversationError: conversation … is closed``) too, is unexpected: its class is
    part of what it says.
    """
    if isinstance(exc, _IN_WORDS):
        return str(exc) or type(exc).__name__
    return f"{type(exc).__name__}: {exc}"


async def wait_for_members(p: FederationPlatform, want: str | None, wait: float) -> bool:
    """Wait (at most ``wait`` s) until ``want`` (or any other platform) is seen, then settle.

    True when it was seen; else the caller asks anyway (it may answer all the same).
    """
    gdf = p.agents.global_df
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline:
        alive = [x for x in (gdf.listed if gdf else []) if x != p.name]
        if (want in alive) if want else alive:
            await asyncio.sleep(min(0.5, max(0.0, deadline - time.monotonic())))
            return True
        await asyncio.sleep(0.1)
    return False


@contextlib.asynccontextmanager
async def reaching(p: FederationPlatform, want: str, wait: float) -> AsyncIterator[None]:
    """Wait for ``want`` to be seen; a request of the body that then fails says it never was.

    The transport's own words ("did not answer the key exchange") do not tell a user that
    the platform is not running, or not reachable with this config, the usual causes.
    """
    seen = await wait_for_members(p, want, wait)
    try:
        yield
    except (TransportError, TimeoutError) as exc:
        if not seen:
            raise NotAnsweredError(
                f"platform {want!r} was not seen in federation {p.config.federation!r} within "
                f"{wait:g} s (--wait) and did not answer ({exc}): is it running, and does "
                f"{p.name}'s [transport] reach it?"
            ) from None
        if isinstance(exc, TransportError) and "key exchange" in str(exc):
            # alive, yet silent to us: what a platform does with a key it does not trust
            raise NotAnsweredError(
                f"{exc}: it is alive, so does it trust {p.name!r}? A platform reads its "
                "trust file when it starts and on SIGHUP ('dyknow node'): send it SIGHUP "
                "after 'dyknow keys trust'"
            ) from None
        raise


def platforms_of(p: FederationPlatform) -> dict[str, list[dict[str, Any]]]:
    """``{platform: [service, …]}`` of those listed, as ``p`` sees them (``p`` left out)."""
    gdf = p.agents.global_df
    if gdf is None:
        return {}
    return {
        name: [{"name": s.name, "type": s.type, "provider": s.provider} for s in gdf.services(name)]
        for name in gdf.listed
        if name != p.name
    }
