"""The simple temporal network of a chronicle: distance graph, minimal network, cycles.

Time points are the chronicle's events; a constraint ``lo <= t(b) - t(a) <= hi`` is the
edges ``a -> b`` (weight ``hi``) and ``b -> a`` (weight ``-lo``), in ns. Floyd–Warshall
tightens every bound to the minimal network; a negative cycle means no assignment of
times meets the constraints, and the error names the constraints on it.
"""

from __future__ import annotations

from ._spec import ChronicleError

_INF = 1 << 62
_NEG_INF = -(1 << 62)


def _floyd_warshall(dist: list[list[int]], why: list[list[str | None]]) -> None:
    """Tighten ``dist`` to all-pairs shortest paths; a negative cycle raises, naming it."""
    n = len(dist)
    nxt = [[j if dist[i][j] < _INF else -1 for j in range(n)] for i in range(n)]
    for k in range(n):
        dk = dist[k]
        for i in range(n):
            dik = dist[i][k]
            if dik >= _INF:
                continue
            di = dist[i]
            for j in range(n):
                if dk[j] >= _INF:
                    continue
                d = dik + dk[j]
                if d < di[j]:
                    di[j] = d
                    nxt[i][j] = nxt[i][k]
            if di[i] < 0:
                raise ChronicleError("constraints", _cycle_message(i, nxt, why))


def _cycle_message(i: int, nxt: list[list[int]], why: list[list[str | None]]) -> str:
    named: list[str] = []
    u = i
    for _ in range(len(nxt) + 1):
        v = nxt[u][i]
        if v < 0:
            break
        w = why[u][v]
        if w is not None and w not in named:
            named.append(w)
        u = v
        if u == i:
            break
    return "inconsistent temporal constraints (negative cycle): " + "; ".join(named)
