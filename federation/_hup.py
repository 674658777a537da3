"""A SIGHUP held from the start of ``dyknow node`` (``console``, ``foxglove``) until the
platform can reload its policy.

A module of its own, so that the light entry (``federation.cli``), which holds the signal
before anything heavy is imported, and the node's run (`_cli_net`), which takes it once
ready, share it without an import cycle.
"""

from __future__ import annotations

import signal

_hup_pending = False  # a SIGHUP came before the node's reload handler was installed


def _held_hup(signum: int, frame: object) -> None:
    global _hup_pending
    _hup_pending = True


def hold_hup() -> None:
    """From the start of ``dyknow node`` (``console``, ``foxglove``): a SIGHUP (whose default
    ends the process) is held until the platform can reload (`take_held_hup`), not fatal
    while it starts."""
    if hasattr(signal, "SIGHUP"):
        signal.signal(signal.SIGHUP, _held_hup)


def take_held_hup() -> bool:
    """Whether a SIGHUP was held since `hold_hup` (and no longer)."""
    global _hup_pending
    pending, _hup_pending = _hup_pending, False
    return pending
