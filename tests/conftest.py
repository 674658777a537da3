"""Shared test settings."""

import os

from hypothesis import HealthCheck, settings

# Shared 2-core machines stall for tens of milliseconds: a per-example deadline only makes
# noise. In CI the examples are derandomized so a red run can be replayed exactly.
settings.register_profile("dev", deadline=None)
settings.register_profile(
    "ci", deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("ci" if os.environ.get("CI") else "dev")
