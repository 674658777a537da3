"""The multi-UAV traffic monitoring demo: a simulated world, UAV platforms, the operator.

`dyknow demo traffic` runs it (see docs/demo.md).
"""

from ._cli import demo_app

__all__ = ["demo_app"]
