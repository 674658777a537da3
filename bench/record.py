"""Recording to MCAP: our Recorder against the raw ``mcap`` writer, on the same samples.

Both run in the same process on the same pre-generated flight (an altitude as a float and
a position as a small dict, two samples per 1 ms step), interleaved, best of ``REPEAT``:

- ours: a DyKnow instance on a manual clock with two sources; a ``Recorder`` follows both
  streams and writes them to an MCAP file; the sources push batches of 1000 samples. The
  time counts the pushes (the instance's streams) and the recording, up to the file closed.
- mcap: ``mcap.writer.Writer`` as a user would drive it for the same file: one JSON schema
  and ``json`` channel per label, each sample ``orjson.dumps`` of the same message (value,
  valid and available time as sec/nsec) added with its log and publish time, a chunk
  flushed every 1000 samples as ours does, zstd, indexed.

Both files are read back with the ``mcap`` library's reader and must hold the same
messages (topic, log time, publish time, decoded message) before a figure is printed.
"""

from __future__ import annotations

import gc
import statistics
import tempfile
from functools import partial
from pathlib import Path
from typing import Any

import orjson
from mcap.reader import make_reader
from mcap.writer import Writer

from bench import fmt, progress, report, timed
from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock, Recorder, Sample

N = 200_000  # samples in all, half per label
BATCH = 1000
REPEAT = 5
T0 = 1_764_000_000 * NS_PER_S  # an epoch clock: the MCAP times are the times
STEP = 1_000_000  # 1 ms between steps
DELAY = 400_000  # available 0.4 ms after valid
LABELS = ("uav/altitude", "uav/position")
_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
SCHEMA = {"type": "object", "properties": {"valid_time": _TIME, "available_time": _TIME}}


def make_flight() -> dict[str, list[Sample]]:
    """The two labels' samples: altitude floats, position dicts."""
    alt, pos = [], []
    for i in range(N // 2):
        tv = T0 + i * STEP
        a = 100.0 + (i % 500) * 0.25
        alt.append(Sample(a, tv, tv + DELAY))
        p = {"lat": 58.39 + i * 1e-7, "lon": 15.57 - i * 1e-7, "alt": a}
        pos.append(Sample(p, tv, tv + DELAY + 1))
    return {LABELS[0]: alt, LABELS[1]: pos}


def run_ours(flight: dict[str, list[Sample]], path: Path) -> None:
    """Push both streams in batches with a Recorder following them; close the file."""
    inst = DyKnowInstance(clock=ManualClock(T0))
    sources = [inst.add_source(label) for label in LABELS]
    rec = Recorder(inst, list(LABELS), path, batch_size=BATCH).start()
    half = BATCH // 2
    for i in range(0, N // 2, half):
        for src, label in zip(sources, LABELS, strict=True):
            src.push_batch(flight[label][i : i + half])
    rec.close()


def run_mcap(flight: dict[str, list[Sample]], path: Path) -> None:
    """The same messages through the raw mcap writer, a chunk per 1000 samples."""
    dumps, ns = orjson.dumps, NS_PER_S
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        channels = {}
        for label in LABELS:
            schema = w.register_schema(label, "jsonschema", dumps(SCHEMA))
            channels[label] = w.register_channel(label, "json", schema)
        add = w.add_message
        half = BATCH // 2
        for i in range(0, N // 2, half):
            for label in LABELS:
                channel = channels[label]
                for value, tv, ta in flight[label][i : i + half]:
                    vs, vn = divmod(tv, ns)
                    as_, an = divmod(ta, ns)
                    msg = {
                        "value": value,
                        "valid_time": {"sec": vs, "nsec": vn},
                        "available_time": {"sec": as_, "nsec": an},
                    }
                    add(channel, ta, dumps(msg), tv)
            w.flush()
        w.finish()


def messages(path: Path) -> list[tuple[str, int, int, Any]]:
    """Every message of a file as the mcap library reads it, in log-time order."""
    with path.open("rb") as f:
        return [
            (ch.topic, m.log_time, m.publish_time, orjson.loads(m.data))
            for _, ch, m in make_reader(f).iter_messages(log_time_order=True)
        ]


def run() -> None:
    """Measure both writers, check the files agree, print samples/s and the BENCH line."""
    progress(f"generating {N:,} samples")
    flight = make_flight()
    with tempfile.TemporaryDirectory() as tmp:
        paths = {"ours": Path(tmp) / "ours.mcap", "mcap": Path(tmp) / "mcap.mcap"}
        runs = {"ours": run_ours, "mcap": run_mcap}
        times: dict[str, list[float]] = {name: [] for name in runs}
        for rep in range(REPEAT):
            for name, fn in runs.items():  # interleaved: a slow spell hits both alike
                gc.collect()
                seconds, _ = timed(partial(fn, flight, paths[name]))
                times[name].append(seconds)
                progress(f"run {rep + 1}/{REPEAT} {name}: {seconds:.2f} s")
        ours, peer = messages(paths["ours"]), messages(paths["mcap"])
        if ours != peer:
            i = next((i for i, (a, b) in enumerate(zip(ours, peer, strict=False)) if a != b), 0)
            raise AssertionError(
                f"ours wrote {len(ours)} messages, mcap {len(peer)}; first difference at "
                f"#{i}: they must agree before any figure means anything"
            )
        sizes = {name: p.stat().st_size for name, p in paths.items()}
    print(f"{N:,} samples, 2 labels; both files hold the same {len(ours):,} messages")
    rate = {name: N / min(ts) for name, ts in times.items()}
    print(f"samples/s, best of {REPEAT} interleaved runs (median in brackets), file size:")
    for name, ts in times.items():
        print(
            f"  {name:<6} {fmt(rate[name]):>8}  ({fmt(N / statistics.median(ts))})  "
            f"{sizes[name] / 1e6:.1f} MB"
        )
    report("record", rate["ours"], "mcap", rate["mcap"], "samples/s", better="higher")
