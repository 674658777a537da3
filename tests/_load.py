"""How loaded the machine running the tests is, measured: for tests that run in real time."""

from __future__ import annotations

import os
import time


def slowdown() -> float:
    """How many times slower than on a machine of its own this process runs now (>= 1).

    Measured: a busy loop's CPU time over its wall time is the share of a CPU it gets (a
    tenth with a load of 20 on 2 cores); the load average says the same over the last
    minute, and whichever is worse counts, a busy spell being short or long.
    """
    t0, c0 = time.monotonic(), time.thread_time()
    while time.monotonic() - t0 < 0.2:
        pass
    share = (time.thread_time() - c0) / (time.monotonic() - t0)
    load = os.getloadavg()[0] / (os.cpu_count() or 1)
    return max(1.0, load, 1.0 / max(share, 0.02))
