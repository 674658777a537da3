"""Export → import between OS processes, authenticated, beside raw zenoh in the same run.

Every platform is its own process (``spawn``), on zenoh in peer mode over loopback
(``bench/_fed_node.py``, ``bench/_fed_proc.py``). The exporter's `ExportProxy` seals each
batch with a real session (ChaCha20-Poly1305, the platforms' default, under keys agreed
by an Ed25519-signed key exchange run over a zenoh query); the receiver's `ImportProxy`
opens it, decodes it, adds the samples to its local stream, and a subscriber with bounds
(``Policy(lower, upper)``) on that stream counts what it gets: that count is "ours".

- ``export-throughput``: the exporter pushes batches of 256 samples into its source as
  fast as the flow control below lets it; ours = samples/s reaching the receiving
  subscriber.
  The peer, in the same process pair, interleaved with ours: raw zenoh put of 64-byte
  messages (DROP, reliable, as ours) counted in the subscriber callback, one message
  per put, no decoding, nothing kept. Also shown: raw zenoh carrying pre-packed msgpack
  batches of 256 samples, unpacked in the callback (the batch ceiling).
- ``export-latency-p99``: samples pushed at 1 kHz, publish → arrival in the receiving
  subscriber, ``time.time_ns()`` at both ends (one host); raw zenoh put → callback at
  1 kHz in the same run, in alternating blocks.
- ``export-throughput-encrypted``: the cost of encryption: ours (encrypted sessions)
  against the same flood over MAC-only sessions, two process pairs, windows alternating.
- ``frozen-receiver``: one exporter, four receivers; the three healthy receivers' summed
  throughput with all four running, then with the fourth SIGSTOPped, alternating; with
  the exporter's counters for the frozen one and, once thawed, what its import counted
  as lost.

Figures are medians over the rounds (every round is printed); rates are measured at the
receivers over a window that starts after a warm-up, between two snapshots. Every flood
(ours and raw alike) is flow-controlled by the bench: the exporter stays at most 32 k
items ahead of what each watched receiver acknowledged counting (acks every 2 ms over
raw zenoh), so what is measured is the rate the path sustains, not a backlog piling up
in a receiver while the sender takes a CPU from it (there are two on these machines).
"""

from __future__ import annotations

import statistics
import time
from typing import Any

from bench import fmt, progress, report
from bench._fed_node import BATCH, RAW_PAYLOAD
from bench._fed_proc import Node, NodeFailed, cluster

ROUNDS = 5
WARM = 0.5  # s of flood before the window opens
WINDOW = 2.0  # s between the two snapshots
TAIL = 0.3  # s the flood goes on after the window closed
HZ = 1000.0
LAT_BLOCK = 500  # samples per block; ours and raw alternate
LAT_BLOCKS = 8  # per kind: 8 x 500 = 4000 samples each
FROZEN_ROUNDS = 3
_KEY = {"ours": "ours", "raw": "raw", "rawbatch": "rawbatch"}


def _window(
    exporter: Node, measured: list[Node], kind: str, watch: list[str], seconds: float = WINDOW
) -> dict[str, Any]:
    """Flood ``kind`` and measure each of ``measured`` over one window: rates and CPU."""
    flood = exporter.send("flood", kind, WARM + seconds + TAIL, watch)
    time.sleep(WARM)
    e0 = exporter.call("snap")
    r0 = [r.call("snap") for r in measured]
    time.sleep(seconds)
    e1 = exporter.call("snap")
    r1 = [r.call("snap") for r in measured]
    flooded = exporter.result(flood, WARM + seconds + TAIL + 20)
    key = _KEY[kind]
    rates = [(b[key] - a[key]) / (b["t"] - a["t"]) for a, b in zip(r0, r1, strict=True)]
    got = sum(b[key] - a[key] for a, b in zip(r0, r1, strict=True))
    return {
        "rates": rates,
        "rx_cpu": [(b["cpu"] - a["cpu"]) / (b["t"] - a["t"]) for a, b in zip(r0, r1, strict=True)],
        "rx_us": [
            1e6 * (b["cpu"] - a["cpu"]) / max(b[key] - a[key], 1)
            for a, b in zip(r0, r1, strict=True)
        ],
        "tx_cpu": (e1["cpu"] - e0["cpu"]) / (e1["t"] - e0["t"]),
        "tx_us_per_got": 1e6 * (e1["cpu"] - e0["cpu"]) / max(got, 1),
        "lost": [b["lost"] - a["lost"] for a, b in zip(r0, r1, strict=True)],
        "inbox_dropped": [
            b["inbox_dropped"] - a["inbox_dropped"] for a, b in zip(r0, r1, strict=True)
        ],
        "e0": e0,
        "e1": e1,
        "flood": flooded,
    }


def _settle(nodes: list[Node], timeout: float = 20.0) -> None:
    """Wait until every node's counts stop moving (its backlog is drained), bounded."""
    deadline = time.monotonic() + timeout
    last = [None] * len(nodes)
    while time.monotonic() < deadline:
        now = [(s["ours"], s["raw"], s["rawbatch"]) for s in (n.call("snap") for n in nodes)]
        if now == last:
            return
        last = now  # type: ignore[assignment]
        time.sleep(0.25)
    progress(f"backlog still draining after {timeout:g} s; going on")


def _pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))]


def throughput_and_latency() -> None:
    """``export-throughput`` and ``export-latency-p99``: one exporter, one receiver."""
    progress("starting an exporter and a receiver (two processes, zenoh peer, loopback)")
    with cluster(1) as (exporter, (receiver,)):
        watch = [receiver.name]
        runs: dict[str, list[dict[str, Any]]] = {"raw": [], "ours": [], "rawbatch": []}
        for i in range(ROUNDS):
            for kind in ("raw", "ours", "rawbatch"):
                progress(f"round {i + 1}/{ROUNDS}: {kind} flood, {WINDOW:g} s window")
                w = _window(exporter, [receiver], kind, watch)
                runs[kind].append(w)
                _settle([receiver])
                print(
                    f"  round {i + 1} {kind:>8}: {fmt(w['rates'][0])}/s at the receiver "
                    f"(exporter sent {fmt(w['flood']['sent'] / w['flood']['seconds'])}/s); "
                    f"CPU exporter {w['tx_cpu']:.2f} cores = {w['tx_us_per_got']:.2f} µs/item, "
                    f"receiver {w['rx_cpu'][0]:.2f} cores = {w['rx_us'][0]:.2f} µs/item; "
                    f"flow control waited {w['flood']['credit_waits']} times"
                    + (f", gave up on {w['flood']['forgiven']}" if w["flood"]["forgiven"] else "")
                    + (
                        f"; lost in transit {w['lost'][0]}, inbox drops {w['inbox_dropped'][0]}"
                        if kind == "ours"
                        else ""
                    ),
                    flush=True,
                )
        ours = statistics.median(w["rates"][0] for w in runs["ours"])
        raw = statistics.median(w["rates"][0] for w in runs["raw"])
        rawbatch = statistics.median(w["rates"][0] for w in runs["rawbatch"])
        paired = [
            o["rates"][0] / r["rates"][0] for o, r in zip(runs["ours"], runs["raw"], strict=True)
        ]
        print(
            f"  per-round ours/raw (adjacent windows): {', '.join(f'{x:.2f}' for x in paired)}; "
            f"median {statistics.median(paired):.2f}"
        )
        print(
            f"  ours: samples/s decoded, opened (encrypted session), injected into the receiving "
            f"stream and delivered to a subscriber with bounds; batches of {BATCH}"
        )
        print(
            f"  zenoh-raw: {RAW_PAYLOAD}-byte messages/s, one put per message (DROP, reliable), "
            "counted in the subscriber callback, payload not even copied"
        )
        print(
            f"  raw batches (not in the ratio): msgpack batches of {BATCH} samples over raw "
            f"zenoh, unpacked in the callback: {fmt(rawbatch)} samples/s; "
            f"ours is {ours / rawbatch:.2f} of it"
        )
        report("export-throughput", ours, "zenoh-raw", raw, "samples/s", better="higher")

        progress(f"latency: {LAT_BLOCKS * LAT_BLOCK} samples each at {HZ:g} Hz, alternating")
        receiver.call("record", True)
        blocks = [("raw", LAT_BLOCK), ("ours", LAT_BLOCK)] * LAT_BLOCKS
        sent = exporter.call("paced", blocks, HZ, timeout=2 * len(blocks) * LAT_BLOCK / HZ + 20)
        time.sleep(0.3)
        got = receiver.call("record", False, timeout=30)
        if len(got["ours"]) < 3000 or len(got["raw"]) < 3000:
            raise NodeFailed(
                f"too few latency samples: ours {len(got['ours'])}/{sent['ours']}, "
                f"raw {len(got['raw'])}/{sent['raw']}"
            )
        lat = {k: [x / 1e6 for x in v] for k, v in got.items()}
        for k in ("ours", "raw"):
            v = lat[k]
            print(
                f"  latency {k:>4} at {HZ:g} Hz: {len(v)}/{sent[k]} samples, "
                f"p50 {_pct(v, 0.5):.3f} ms, p99 {_pct(v, 0.99):.3f} ms, "
                f"max {max(v):.3f} ms"
            )
        print(
            "  ours: push into the exporter's source → its subscriber → export queue → "
            "seal → zenoh → import inbox → open → decode → inject → bounded subscriber; "
            "zenoh-raw: put → subscriber callback"
        )
        report(
            "export-latency-p99",
            _pct(lat["ours"], 0.99),
            "zenoh-raw",
            _pct(lat["raw"], 0.99),
            "ms",
            better="lower",
        )


def _healthy_latency(exporter: Node, healthy: list[Node], n: int = 1000) -> list[float]:
    """Publish ``n`` samples at ``HZ``; each healthy receiver's publish → arrival, in ms."""
    for r in healthy:
        r.call("record", True)
    exporter.call("paced", [("ours", n)], HZ, timeout=2 * n / HZ + 20)
    time.sleep(0.2)
    out: list[float] = []
    for r in healthy:
        got = r.call("record", False, timeout=30)["ours"]
        if len(got) < 0.9 * n:
            raise NodeFailed(f"{r.name} got {len(got)} of {n} latency samples")
        out.extend(x / 1e6 for x in got)
    return out


def frozen_receiver() -> None:
    """``frozen-receiver``: three healthy receivers' throughput, with and without a frozen one."""
    progress("starting an exporter and four receivers (five processes)")
    with cluster(4) as (exporter, receivers):
        healthy, victim = receivers[:3], receivers[3]
        watch = [r.name for r in healthy]
        base: list[float] = []
        frozen: list[float] = []
        lat_base: list[float] = []
        lat_frozen: list[float] = []
        for i in range(FROZEN_ROUNDS):
            for phase in ("none frozen", "one frozen"):
                progress(f"round {i + 1}/{FROZEN_ROUNDS}: {phase}")
                if phase == "one frozen":
                    lost0 = victim.call("snap")["lost"]
                    v0 = exporter.call("snap")["exports"][victim.name]
                    victim.freeze()
                    time.sleep(0.2)
                    w = _window(exporter, healthy, "ours", watch)
                    _settle(healthy)
                    lat = _healthy_latency(exporter, healthy)
                    v1 = exporter.call("snap")["exports"][victim.name]
                    victim.thaw()
                else:
                    w = _window(exporter, receivers, "ours", watch)
                    _settle(receivers)
                    lat = _healthy_latency(exporter, healthy)
                _settle(receivers)
                (lat_frozen if phase == "one frozen" else lat_base).extend(lat)
                total = sum(w["rates"][:3])
                (frozen if phase == "one frozen" else base).append(total)
                per = ", ".join(fmt(r) for r in w["rates"])
                line = (
                    f"  round {i + 1} {phase}: healthy three {fmt(total)} samples/s ({per}); "
                    f"exporter CPU {w['tx_cpu']:.2f} cores; then at {HZ:g} Hz the healthy "
                    f"three's latency p50 {_pct(lat, 0.5):.3f} ms, p99 {_pct(lat, 0.99):.3f} ms"
                )
                if phase == "one frozen":
                    # a gap shows once a later batch arrives: send one after the backlog
                    exporter.call("push", 16)
                    time.sleep(0.3)
                    _settle(receivers)
                    lost = victim.call("snap")["lost"] - lost0
                    line += (
                        f"\n    frozen receiver's export while it was frozen: sent "
                        f"{v1['sent'] - v0['sent']} samples in {v1['batches'] - v0['batches']} "
                        f"batches, dropped {v1['dropped'] - v0['dropped']} "
                        f"(by reason, cumulative: {v1['dropped_by_reason'] or 'none'}), "
                        f"queued {v1['queued']}, last error {v1['last_error']}"
                        f"\n    once thawed, its import counted {lost} samples lost in transit "
                        f"({lost / max(v1['sent'] - v0['sent'], 1):.0%} of those; sequence "
                        "gaps: dropped inside zenoh (congestion control DROP), which the "
                        "exporter's counters never see)"
                    )
                print(line, flush=True)
        ours = statistics.median(frozen)
        baseline = statistics.median(base)
        print(
            f"  healthy three's latency at {HZ:g} Hz over all rounds: none frozen p50 "
            f"{_pct(lat_base, 0.5):.3f} / p99 {_pct(lat_base, 0.99):.3f} ms, one frozen p50 "
            f"{_pct(lat_frozen, 0.5):.3f} / p99 {_pct(lat_frozen, 0.99):.3f} ms"
        )
        print("  ours: healthy receivers' summed samples/s with the fourth SIGSTOPped;")
        print("  baseline: the same three, all four receivers running (the exporter floods,")
        print("  flow-controlled by the healthy three only; five processes share two cores)")
        report("frozen-receiver", ours, "baseline", baseline, "samples/s", better="higher")


def encryption_cost() -> None:
    """``export-throughput-encrypted``: encrypted against MAC-only sessions, alternating.

    One exporter/receiver pair: before each window both switch their policy and the
    exporter agrees a new session under it, so the same two processes carry both kinds
    (two pairs differed by more than encryption costs); which kind goes first alternates.
    """
    progress("starting an exporter and a receiver: encrypted and MAC-only sessions in turn")
    with cluster(1) as (exporter, (receiver,)):
        rates: dict[str, list[float]] = {"encrypted": [], "plain": []}
        kinds = [("encrypted", True), ("plain", False)]
        for i in range(ROUNDS):
            for kind, on in kinds if i % 2 == 0 else kinds[::-1]:
                receiver.call("encrypt", on)
                sid = exporter.call("encrypt", on, timeout=15)
                _settle([receiver])
                progress(f"round {i + 1}/{ROUNDS}: {kind} session {sid}, {WINDOW:g} s window")
                w = _window(exporter, [receiver], "ours", [receiver.name])
                rates[kind].append(w["rates"][0])
                print(
                    f"  round {i + 1} {kind:>9}: {fmt(w['rates'][0])}/s at the receiver; "
                    f"CPU exporter {w['tx_us_per_got']:.2f} µs/item, "
                    f"receiver {w['rx_us'][0]:.2f} µs/item",
                    flush=True,
                )
        enc = statistics.median(rates["encrypted"])
        plain = statistics.median(rates["plain"])
        paired = [e / p for e, p in zip(rates["encrypted"], rates["plain"], strict=True)]
        print(f"  per-round encrypted/plain: {', '.join(f'{x:.2f}' for x in paired)}")
        print("  encrypted: ChaCha20-Poly1305 batches (default); plain: HMAC-SHA256 only")
        report("export-throughput-encrypted", enc, "plain", plain, "samples/s", better="higher")


def run() -> None:
    """Run the federation benchmarks and print their BENCH lines."""
    throughput_and_latency()
    encryption_cost()
    frozen_receiver()
