"""SIGHUP for ``dyknow node`` (``console``, ``foxglove``): held from the start until the
platform can reload its policy, then a reload each.

A module of its own, so that the light entry (``federation.cli``), which holds the signal
before anything heavy is imported, and the platform's run (`_cli_net`), which takes it
once ready, share it without an import cycle.

One Python handler throughout, not the event loop's (``add_signal_handler``): a SIGHUP
that comes while the loop's handler is being installed would be held here and also
replayed by the loop (its wakeup byte), so applied twice.
"""

from __future__ import annotations

import signal
from collections.abc import Callable

_hup_pending = False  # a SIGHUP came before the platform could reload
_action: Callable[[], object] | None = None  # what a SIGHUP does once it can


def _on_hup(signum: int, frame: object) -> None:
    global _hup_pending
    if _action is not None:
        _action()
    else:
        _hup_pending = True


def hold_hup() -> None:
    """From the start of ``dyknow node`` (``console``, ``foxglove``): a SIGHUP (whose default
    ends the process) is held until the platform can reload (`on_hup`), not fatal while
    it starts."""
    if hasattr(signal, "SIGHUP"):
        signal.signal(signal.SIGHUP, _on_hup)


def on_hup(action: Callable[[], object] | None) -> None:
    """From now on each SIGHUP calls ``action`` (in the main thread, between two bytecodes:
    it must only schedule work); one held since `hold_hup` calls it now, once. None: SIGHUP
    is ignored from now on (the platform stops; never the default, which ends the process).
    """
    global _action, _hup_pending
    if not hasattr(signal, "SIGHUP"):
        return
    if action is None:
        _action = None
        signal.signal(signal.SIGHUP, signal.SIG_IGN)  # in one step: never the default
        return
    _action = action  # first: a SIGHUP from here on calls it, none is held any more
    signal.signal(signal.SIGHUP, _on_hup)
    pending, _hup_pending = _hup_pending, False
    if pending:
        action()
