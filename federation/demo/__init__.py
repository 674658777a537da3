"""The multi-UAV traffic monitoring demo: a simulated world, UAV platforms, the operator.

`dyknow demo traffic` runs it (see docs/demo.md).
"""
