"""Runnable examples: one small script per capability, each a module with ``main()``."""
