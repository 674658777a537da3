"""Text another platform chose, fit for one line of our log or audit.

A reason another platform wrote (why it ended an export, why it bounced an inform, what
it asked for that we refused) is its word: logged, but bounded. `quoted` escapes what
could break the line (a newline would forge a log line of ours; a terminal escape would
rewrite what the operator sees) and caps its length, saying how long it was. A refusal
or an audit record that echoes such words quotes them so too (docs/security.md).
"""

from __future__ import annotations

__all__ = ["QUOTE_MAX", "quoted"]

QUOTE_MAX = 200  # characters of another platform's text kept in one log line


def quoted(text: object, limit: int = QUOTE_MAX) -> str:
    """``text`` on one line: control and format characters escaped, cut at ``limit``."""
    s = str(text)
    if len(s) <= limit and s.isprintable():
        return s  # the common case, at C speed: nothing to escape or cut
    out: list[str] = []
    size = 0
    for i, c in enumerate(s):
        if not c.isprintable():  # newlines, escapes, bidirectional overrides
            n = ord(c)
            c = f"\\x{n:02x}" if n < 0x100 else f"\\u{n:04x}" if n < 0x10000 else f"\\U{n:08x}"
        size += len(c)
        if size > limit:
            return "".join(out) + f"… ({len(s)} characters, {len(s) - i} left out)"
        out.append(c)
    return "".join(out)
