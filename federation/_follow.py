"""Following another member's stream: what the operator console and the Foxglove bridge share.

A follower asks the member for a label (``create-stream``, again while refused), waits
for the import to appear here, subscribes to it from where it last was and hands every
batch to its owner; when the stream ends while the member is alive (its lease for us
expired), it asks again. `FollowedStream` is what it keeps of one label of one member;
`follow` runs it; `cancel_export` ends what was agreed. `BadValues` counts the samples
a follower could not take, their log lines bounded.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from dyknow_core import Policy

from ._quote import quoted

if TYPE_CHECKING:
    from ._platform import FederationPlatform

__all__ = [
    "BAD_VALUE_LOG_INTERVAL",
    "REQUEST_TIMEOUT",
    "RETRY",
    "WAIT_IMPORT",
    "BadValues",
    "FollowedStream",
    "StreamState",
    "cancel_export",
    "follow",
    "reason",
]

log = logging.getLogger("federation.follow")

RETRY = 2.0  # s: between attempts at a stream a platform refused or ended
WAIT_IMPORT = 5.0  # s: one wait for the first sample of a stream (then waits again)
REQUEST_TIMEOUT = 5.0  # s: one request to another platform
BAD_VALUE_LOG_INTERVAL = 1.0  # s: a stream's bad values after its first: one line per interval

StreamState = Literal["requesting", "active", "refused", "ended"]


@dataclass(slots=True)
class FollowedStream:
    """One label of another member as a follower asks for it and takes it in.

    ``export_id`` is the provider's export for us (None: none agreed now); ``lock`` is
    held while it changes, so that a change of policy and a renewed request never ask
    twice; ``error`` is why the member refused it, as `quoted` bounds it; ``last_valid``
    (ns) is where a new subscription resumes.
    """

    label: str
    sample_period: float | None = None
    state: StreamState = "requesting"
    export_id: str | None = None
    error: str | None = None
    last_valid: int | None = None
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    refused_before: bool = False  # since it last flowed: its agreement is then said too


class BadValues:
    """The samples of followed streams their follower could not take: counted, logged bounded.

    A stream's first bad value is logged at once; those after it at most one line per
    `BAD_VALUE_LOG_INTERVAL`, the next one let through saying how many were held back
    before it, and `close` says what is still held: a member sending bad values at
    1 kHz must not flood the operator's log. A line names the value's type and the
    error's, never the value nor the error's text (which may quote it): the value came
    encrypted from its platform. ``counts`` has every one, by stream.
    """

    def __init__(self, logger: logging.Logger, interval: float | None = None) -> None:
        self.log = logger  # the follower's
        self.interval = BAD_VALUE_LOG_INTERVAL if interval is None else interval
        self.counts: dict[str, int] = {}  # stream ("<platform>/<label>"): bad values so far
        self._next: dict[str, float] = {}  # stream: when its next line may be logged
        self._held: dict[str, tuple[int, str, str]] = {}  # stream: held, where, latest kinds

    def add(self, stream: str, where: str, value: Any, exc: BaseException) -> None:
        """Count a bad value of ``stream``; log it (``where`` first) unless one was just."""
        total = self.counts[stream] = self.counts.get(stream, 0) + 1
        kinds = f"({type(value).__name__}): {type(exc).__name__}"
        now = time.monotonic()
        if now < self._next.get(stream, -math.inf):
            held = self._held.get(stream, (0, "", ""))[0]
            self._held[stream] = (held + 1, where, kinds)
            return
        self._next[stream] = now + self.interval
        held = self._held.pop(stream, (0, "", ""))[0]
        if held:
            self.log.warning(
                "%s: bad value %s (and %d more held back before it; %d in all)",
                where,
                kinds,
                held,
                total,
            )
        else:
            self.log.warning("%s: bad value %s", where, kinds)

    def close(self) -> None:
        """Log what is still held back, one line per stream (its follower is closing)."""
        for stream, (held, where, kinds) in self._held.items():
            self.log.warning(
                "%s: %d more bad values held back, the latest %s; %d in all",
                where,
                held,
                kinds,
                self.counts[stream],
            )
        self._held.clear()

    def stats(self) -> dict[str, Any]:
        """``bad_values`` by stream and their total, as the follower's stats say them."""
        return {"bad_values": dict(self.counts), "bad_values_total": sum(self.counts.values())}


def _always() -> bool:
    return True


def _nothing() -> None:
    return None


async def follow(
    platform: FederationPlatform,
    member: str,
    stream: FollowedStream,
    feed: Callable[[list[Any]], None],
    *,
    ask: bool = True,
    alive: Callable[[], bool] = _always,
    changed: Callable[[], None] = _nothing,
) -> None:
    """Follow ``stream`` at ``member``, handing each batch of its import to ``feed``.

    With ``ask`` it is asked for (again while refused, and only while ``alive()``);
    without, what another asked for is taken in. When the import ends it starts over
    while ``alive()``, else returns. ``changed()`` is called after every change of
    ``stream.state``. Runs until cancelled or the member is no longer alive.
    """
    while True:
        if ask:
            await _ask_for(platform, member, stream, alive, changed)
        await _take_in(platform, member, stream, feed)
        if not alive():
            return
        # ended while its platform is alive (it stopped exporting to us: its lease for us
        # expired): ask for it again
        async with stream.lock:
            stream.export_id, stream.state = None, "requesting"
        changed()
        await asyncio.sleep(RETRY)


async def _ask_for(
    platform: FederationPlatform,
    member: str,
    stream: FollowedStream,
    alive: Callable[[], bool],
    changed: Callable[[], None],
) -> None:
    fed = platform.federation_agent
    while True:
        if alive():
            async with stream.lock:
                if stream.export_id is not None:
                    return  # a policy change got it meanwhile
                try:
                    stream.export_id = await fed.create_stream(
                        member,
                        [stream.label],
                        sample_period=stream.sample_period,
                        timeout=REQUEST_TIMEOUT,
                    )
                except Exception as exc:
                    # the member's word on why: bounded, one line, in the log as on the
                    # page and in /api/state (100 kB of it would be sent every refresh)
                    why = quoted(reason(exc))
                    # said once per refusal: a page shows it, but a log may be all one sees
                    # (dyknow foxglove); asked again every RETRY s, each time at info
                    again = stream.state == "refused" and stream.error == why
                    stream.state, stream.error = "refused", why
                    stream.refused_before = True
                    (log.info if again else log.warning)(
                        "%s refused %s to %s: %s (asked again every %g s)",
                        member,
                        stream.label,
                        platform.name,
                        quoted(exc),
                        RETRY,
                    )
                    changed()
                else:
                    agreed(stream, member, platform.name)
                    changed()
                    return
        await asyncio.sleep(RETRY)


async def _take_in(
    platform: FederationPlatform,
    member: str,
    stream: FollowedStream,
    feed: Callable[[list[Any]], None],
) -> None:
    while True:
        try:
            local = await platform.imported(member, stream.label, timeout=WAIT_IMPORT)
            break
        except TimeoutError:
            continue  # a platform may have nothing to say yet (no violation so far)
    # From the start of time the first time: the cache replays what arrived before we
    # subscribed (at least the sample that opened the stream, perhaps its only one);
    # after that, a platform come back included, from where we were (nothing twice).
    start = 0 if stream.last_valid is None else stream.last_valid + 1
    with platform.instance.subscribe(local, Policy(start=start)) as sub:
        async for batch in sub.batches():
            if batch:
                newest = max([s[1] for s in batch])
                if stream.last_valid is None or newest > stream.last_valid:
                    stream.last_valid = newest
            feed(batch)


def agreed(stream: FollowedStream, member: str, follower: str) -> None:
    """Mark ``stream`` active: ``member`` agreed it. After a refusal, say so (a warning)."""
    stream.state, stream.error = "active", None
    if stream.refused_before:  # the refusal was a warning: so is its end, once
        stream.refused_before = False
        log.warning("%s now streams %s to %s (refused before)", member, stream.label, follower)


async def cancel_export(platform: FederationPlatform, member: str, stream: FollowedStream) -> None:
    """Ask ``member`` to stop the export agreed for ``stream`` (best effort: failures logged)."""
    export_id, stream.export_id = stream.export_id, None
    if export_id is None:
        return
    try:
        await platform.federation_agent.cancel_stream(member, export_id, timeout=REQUEST_TIMEOUT)
    except Exception as exc:  # the export may be gone with its platform already
        # the member's word on why: bounded, one line
        log.info("cancelling %s at %s: %s", export_id, member, quoted(reason(exc)))


def reason(exc: BaseException) -> str:
    """What went wrong, for a person: a refusal's content, else the exception's text."""
    message = getattr(exc, "message", None)
    content = getattr(message, "content", None)
    if isinstance(content, str) and content:
        return f"{type(exc).__name__.lower()}: {content}"
    return str(exc) or type(exc).__name__
