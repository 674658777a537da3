"""Text another platform chose, fit for one line of our log: `agents.quoted`, here too."""

from agents import QUOTE_MAX, quoted

__all__ = ["QUOTE_MAX", "quoted"]
