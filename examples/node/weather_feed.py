"""A Python input (``kind = "python"``): any async generator of messages feeds a node."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import AsyncIterator
from typing import Any


async def readings(period: float = 0.2, count: int | None = None) -> AsyncIterator[dict[str, Any]]:
    """A simulated station: one reading every ``period`` s (``count`` of them, or for ever)."""
    n = 0
    while count is None or n < count:
        t = time.time()
        yield {"time": t, "temperature": 20.0 + math.sin(n / 10), "wind": 3.0 + n % 5}
        n += 1
        await asyncio.sleep(period)
