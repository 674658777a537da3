"""The budget of presence changes acted on per peer: presence is not authenticated.

Anyone on the network may declare a liveliness token, or write a retained MQTT presence,
under a trusted platform's name. The Interface Agent (doubting the peer's sessions) and
the global directory (asking the peer a signed query) each act on a peer's presence
changes within a budget of the same size: `PRESENCE_BURST` at once, then
`PRESENCE_RATE` per the channel's ``rehandshake_interval``. Each keeps its own bucket, so
a peer's changes are acted on up to twice that overall (once by each). See
``docs/security.md`` ("Presence within a budget").
"""

from __future__ import annotations

from ._bucket import TokenBucket

PRESENCE_BURST = 4
"""Presence changes of one peer acted on at once (a restart is two: gone, then back)."""
PRESENCE_RATE = 2.0
"""Presence changes of one peer acted on per ``rehandshake_interval`` past its burst."""


def presence_bucket(interval: float, now: float) -> TokenBucket:
    """A peer's budget of presence changes acted on, for a ``rehandshake_interval`` in s."""
    return TokenBucket(PRESENCE_RATE / max(interval, 1e-3), PRESENCE_BURST, now)
