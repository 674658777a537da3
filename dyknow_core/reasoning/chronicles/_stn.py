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


class TemporalNetwork:
    """A simple temporal network over ``n`` time points, as its distance graph (ns)."""

    def __init__(self, n: int) -> None:
        # dist[i][j]: upper bound of t_j - t_i; why[i][j]: the constraint that set it
        self.dist = [[_INF] * n for _ in range(n)]
        self.why: list[list[str | None]] = [[None] * n for _ in range(n)]
        for i in range(n):
            self.dist[i][i] = 0

    def constrain(self, a: int, b: int, lo: int | None, hi: int | None, text: str) -> None:
        """Add ``lo <= t_b - t_a <= hi`` (None: unbounded), ``text`` naming it in errors."""
        dist, why = self.dist, self.why
        if hi is not None and hi < dist[a][b]:
            dist[a][b] = hi
            why[a][b] = text
        if lo is not None and -lo < dist[b][a]:
            dist[b][a] = -lo
            why[b][a] = text

    def minimal(self) -> list[list[int]]:
        """The minimal network's distances; ``ChronicleError`` naming a negative cycle."""
        _floyd_warshall(self.dist, self.why)
        return self.dist


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
