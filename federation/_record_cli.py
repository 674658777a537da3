"""``dyknow record`` and ``dyknow replay``: flights to a file, and back through a local instance.

``record`` joins the federation like ``dyknow stream`` (a create-stream from a platform to
this one) and writes what arrives to an MCAP recording (``dyknow_core.Recorder``).
``replay`` pushes a recording (ours, any MCAP file, a rosbag2 bag, an old ``.dkr``)
through a fresh local instance on a manual clock, optionally with a KPL application set
up on it, and prints what its processes produce.
"""

from __future__ import annotations

import asyncio
import dataclasses
import datetime as dt
import json
import sys
import time
from collections.abc import Callable, Iterator
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dyknow_core import (
    DyKnowInstance,
    ManualClock,
    RecordedSample,
    Recorder,
    RecordError,
    Recording,
    ns_to_seconds,
    replay,
)
from dyknow_core.kpl import (
    AnchoringDecl,
    ClassDecl,
    KPLCheckError,
    KPLSetupError,
    Program,
    SourceDecl,
    provides,
)
from dyknow_core.kpl import parse as parse_kpl
from dyknow_core.kpl import setup as setup_kpl

from ._cli_net import _exported, _opened, _stop_event, own_without_node
from ._cli_time import seconds, when, when_ns

if TYPE_CHECKING:
    from ontology import LabelMapping

    from ._ros import RosbagRecording


Say = Callable[[str], None]


class ReplayUsageError(Exception):
    """A replay that cannot start: a bad file, spec or label (exit code 2)."""


def jsonable(value: Any) -> Any:
    """A value as JSON can carry it: named tuples and dataclasses become objects."""
    if isinstance(value, tuple) and hasattr(value, "_asdict"):
        return {k: jsonable(v) for k, v in value._asdict().items()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Enum):
        return jsonable(value.value)
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [jsonable(v) for v in value]
    if isinstance(value, bytes):
        return value.hex()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return repr(value)


def _span(lo: int, hi: int) -> str:
    """A span of sample times (ns) as text: ``from .. to (duration)``."""
    return f"{when_ns(lo)} .. {when_ns(hi)} ({seconds(ns_to_seconds(hi - lo))})"


def _created(text: str) -> str:
    """A recording's creation stamp (ISO 8601, UTC) as the CLI shows times."""
    try:
        return when(dt.datetime.fromisoformat(text).timestamp())
    except ValueError:
        return text


# -- record -------------------------------------------------------------------------------------


async def record_federation(
    config_path: str,
    platform: str,
    semantic_labels: list[str],
    out: Path,
    *,
    duration: float | None,
    count: int | None,
    sample_period: float | None,
    wait: float,
    timeout: float,
    progress: Say,
) -> Recorder:
    """Create-stream ``semantic_labels`` from ``platform`` and record them until a stop.

    Stops on SIGINT/SIGTERM, after ``duration`` seconds or ``count`` samples; the file is
    complete in every case. ``progress`` gets a line with the counts at most every second.
    When a node of this config runs here, its samples come through it (`_record_relayed`).
    """
    relayed = await _record_relayed(
        config_path,
        platform,
        semantic_labels,
        out,
        duration=duration,
        count=count,
        sample_period=sample_period,
        wait=wait,
        timeout=timeout,
        progress=progress,
    )
    if relayed is not None:
        return relayed
    own_without_node(config_path, platform, "record")
    async with _opened(config_path) as p:
        stop = _stop_event()  # after opening: zenoh installs handlers of its own
        since = p.instance.clock.now()
        async with _exported(
            p, platform, semantic_labels, sample_period=sample_period, wait=wait, timeout=timeout
        ):
            local = {
                await p.imported(platform, semantic, timeout=timeout): semantic
                for semantic in semantic_labels
            }
            meta = {
                "platform": platform,
                "recorded_by": p.name,
                "federation": p.config.federation,
                "sample_period": sample_period,
            }
            # ``since``: what arrived while the imports were being looked up is kept too
            rec = Recorder(
                p.instance, list(local), out, rename=local, meta=meta, since=since, limit=count
            )
            async with rec:
                await _until_stopped(rec, stop, duration, progress)
    return rec


async def _record_relayed(
    config_path: str,
    platform: str,
    semantic_labels: list[str],
    out: Path,
    *,
    duration: float | None,
    count: int | None,
    sample_period: float | None,
    wait: float,
    timeout: float,
    progress: Say,
) -> Recorder | None:
    """Record what the running node of this config relays (None when none runs).

    The relayed samples are pushed, with their own valid and available times, into a
    local instance of this command's, which the recorder follows as it would the node's.
    """
    from dyknow_core import DyKnowInstance

    from ._cli_net import stream_through_node
    from ._local import NodeUnreachable, channel_path
    from ._platform import PlatformConfig

    config = PlatformConfig.load(config_path)
    try:
        if not channel_path(config).exists():
            return None
    except NodeUnreachable:  # the key is unusable: acting as the platform says why
        return None
    stop = _stop_event()
    async with DyKnowInstance(f"{config.name}.record") as inst:
        sources = {s: inst.add_source(s) for s in semantic_labels}
        meta = {
            "platform": platform,
            "recorded_by": config.name,
            "federation": config.federation,
            "sample_period": sample_period,
            "through": "the running node",
        }
        # written beside ``out`` and renamed once relayed: a refused request (an unknown
        # label, a platform not there) must not leave an empty file in place of one there
        part = out.with_name(f".{out.name}.part")
        rec = Recorder(inst, semantic_labels, part, meta=meta, since=0, limit=count)

        def emit(label: str, value: Any, valid: int, available: int) -> None:
            sources[label].push(value, valid, available)

        async def relayed() -> int | Exception | None:
            # its failure is returned, to be raised as itself (a group would wrap it)
            try:
                return await stream_through_node(
                    config_path,
                    platform,
                    semantic_labels,
                    sample_period=sample_period,
                    count=count,
                    wait=wait,
                    timeout=timeout,
                    emit=emit,
                    stop=stop,
                )
            except Exception as exc:
                return exc

        error: Exception | None = None
        async with rec, asyncio.TaskGroup() as tg:
            relay = tg.create_task(relayed(), name=f"record.relay[{platform}]")
            ended = asyncio.Event()
            relay.add_done_callback(lambda _: ended.set())
            try:
                await _until_stopped(rec, stop, duration, progress, also=ended)
            except Exception as exc:  # raised below: the group would wrap it
                error = exc
            finally:
                relay.cancel()
    result = None if error is not None or relay.cancelled() else relay.result()
    failed = error if error is not None else result if isinstance(result, Exception) else None
    if rec.recorded or (failed is None and (result is not None or relay.cancelled())):
        # what was recorded is kept, even when the relay failed later (the node stopped)
        part.replace(out)
        rec.path = out
    else:
        part.unlink(missing_ok=True)
    if failed is not None:
        raise failed
    if result is None and not relay.cancelled():
        return None  # a stale socket, nobody listening: record as the platform itself
    return rec


async def _until_stopped(
    rec: Recorder,
    stop: asyncio.Event,
    duration: float | None,
    progress: Say,
    also: asyncio.Event | None = None,
) -> None:
    """Wait for a signal, the duration or the count; a progress line each second it changed."""
    started = time.monotonic()
    deadline = None if duration is None else started + duration
    shown = 0  # no line before the first sample: a refusal comes first, alone
    also = also or asyncio.Event()
    loop = asyncio.get_running_loop()
    waits = {
        loop.create_task(e.wait(), name=f"record.until[{what}]")
        for what, e in (("stop", stop), ("done", rec.done), ("also", also))
    }
    try:
        while not (stop.is_set() or rec.done.is_set() or also.is_set()):
            step = 1.0 if deadline is None else min(1.0, deadline - time.monotonic())
            if step <= 0:
                break
            await asyncio.wait(waits, timeout=step, return_when=asyncio.FIRST_COMPLETED)
            if rec.recorded != shown:
                shown = rec.recorded
                counts = ", ".join(f"{k}={n}" for k, n in sorted(rec.counts.items()))
                elapsed = time.monotonic() - started
                progress(
                    f"recording {rec.path}: {shown} samples ({counts or '-'}) "
                    f"{seconds(round(elapsed))}"
                )
    finally:
        for w in waits:
            w.cancel()
        await asyncio.wait(waits)  # none outlives this call


# -- replay -------------------------------------------------------------------------------------


def open_recording(path: Path) -> Recording | RosbagRecording:
    """Open a recording or raise ReplayUsageError naming the file and what is wrong.

    A directory is a rosbag2 bag; a file is read by ``dyknow_core.Recording`` (our MCAP
    recordings, any MCAP file with its ROS 2 channels decoded, an old ``.dkr``).
    """
    from ._ros import RosbagRecording, cdr_decoder

    try:
        if path.is_dir():
            if not (path / "metadata.yaml").is_file():
                raise RecordError(
                    f"{path}: is a directory, not a recording (nor a rosbag2 bag: it has "
                    "no metadata.yaml)"
                )
            return RosbagRecording(path)
        return Recording(path, decoders={"cdr": cdr_decoder()})
    except RecordError as exc:
        raise ReplayUsageError(str(exc)) from None


def info(path: Path) -> dict[str, Any]:
    """The header and per-label counts of a recording."""
    try:
        return open_recording(path).info()
    except RecordError as exc:
        raise ReplayUsageError(str(exc)) from None


_FORMATS = {"mcap": "MCAP", "rosbag2": "rosbag2", "dkr": ".dkr"}


def info_lines(data: dict[str, Any]) -> list[str]:
    """``dyknow replay --info`` as text."""
    kind = _FORMATS.get(data["format"], data["format"])
    lines = [f"file:       {data['file']}"]
    if data["version"]:
        lines += [
            f"format:     {kind}, dyknow-record version {data['version']}"
            + (f" ({data['library']})" if data["library"] else ""),
            f"instance:   {data['instance']!r} ({data['clock']}, start {when_ns(data['start'])})",
            f"created:    {_created(data['created'])}",
            "labels:     "
            + ("every stream" if data["labels"] is None else ", ".join(data["labels"])),
        ]
        if data["format"] == "mcap":
            lines.append(
                f"offset:     {data['time_offset']} ns (MCAP log time = available time + "
                "offset, publish time = valid time + offset)"
            )
    else:
        lines += [
            f"format:     {kind}, written by {data['library'] or 'an unnamed writer'} (topics "
            "are labels, log times available times)",
            f"start:      {when_ns(data['start'])}",
            f"topics:     {', '.join(data['labels'] or []) or '-'}",
        ]
    for k, v in sorted(data["meta"].items()):
        lines.append(f"meta.{k}: {v}")
    lines.append(f"samples:    {data['samples']}")
    for label, n in data["counts"].items():
        lines.append(f"  {label}: {n}")
    for topic, n in data["undecodable"].items():
        lines.append(f"  {topic}: {n} not decoded ({data['problems'].get(topic, '?')})")
    if data["valid_span"] is not None:
        lo, hi = data["valid_span"]
        lines.append(f"valid time: {_span(lo, hi)}")
    if data["truncated"]:
        lines.append("truncated:  yes (its writer did not finish; read up to the last chunk)")
    return lines


def _read_spec(kpl: Path) -> Program:
    try:
        text = kpl.read_text(encoding="utf-8")
    except OSError as exc:
        raise ReplayUsageError(f"{kpl}: cannot read: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ReplayUsageError(f"{kpl}: not UTF-8 text: {exc.reason}") from None
    try:
        return parse_kpl(text)
    except KPLCheckError as exc:
        raise ReplayUsageError("\n".join(e.format(str(kpl)) for e in exc.errors)) from None


class _Renamed:
    """A recording read under other labels: a node's mapping, semantic → local."""

    __slots__ = ("rec", "rename")

    def __init__(self, rec: Recording | RosbagRecording, rename: dict[str, str]) -> None:
        self.rec = rec
        self.rename = rename

    @property
    def truncated(self) -> bool:
        """Whether the recording's writer did not finish (read up to its last chunk)."""
        return bool(getattr(self.rec, "truncated", False))

    def __iter__(self) -> Iterator[RecordedSample]:
        rename = self.rename
        for s in self.rec:
            local = rename.get(s.label)
            yield s if local is None else s._replace(label=local)


def load_mapping(config_path: Path) -> tuple[LabelMapping, Path | None]:
    """A node config's label mapping and application (KPL) path, for ``replay --config``."""
    from ontology import LabelMapping, OntologyError, Vocabulary

    from ._platform import PlatformConfig, PlatformConfigError

    try:
        config = PlatformConfig.load(config_path)
    except PlatformConfigError as exc:
        raise ReplayUsageError(str(exc)) from None
    try:
        if isinstance(config.vocabulary, Path):
            vocabulary = Vocabulary.load(config.vocabulary)
        else:
            vocabulary = Vocabulary.from_dict(config.vocabulary, source=f"{config_path}")
        if isinstance(config.mapping, Path):
            mapping = LabelMapping.load(config.mapping, vocabulary)
        else:
            mapping = LabelMapping.from_dict(config.mapping, vocabulary, source=f"{config_path}")
    except (OntologyError, OSError) as exc:
        raise ReplayUsageError(f"{config_path}: {exc}") from None
    return mapping, config.application


def _spec_labels(program: Program) -> tuple[set[str], set[str]]:
    """What a spec provides: (computed, declared sources); replay recomputes the first."""
    computed: set[str] = set()
    spec_sources: set[str] = set()
    for d in program.decls:
        provided = set(provides(d))
        (spec_sources if isinstance(d, SourceDecl) else computed).update(provided)
        if isinstance(d, ClassDecl):
            computed.add(f"domain/{d.name}")  # anchoring publishes each class's domain
    if any(isinstance(d, ClassDecl) for d in program.decls) and not any(
        isinstance(d, AnchoringDecl) for d in program.decls
    ):
        computed.add("events/anchoring")
    return computed, spec_sources


def recorded_labels(path: Path, mapping: LabelMapping | None = None) -> list[str]:
    """The labels recorded in ``path``, under ``mapping``'s local ones where it has them.

    ReplayUsageError names the file when it is no recording (or cannot be read).
    """
    counts = list(info(path)["counts"])
    rename = {} if mapping is None else _local_labels(counts, mapping)
    return [rename.get(label, label) for label in counts]


def replayed_labels(recorded: list[str], program: Program) -> list[str]:
    """The streams `run_replay` makes from a recording before it sets ``program`` up.

    The ``recorded`` labels (`recorded_labels`) that the spec neither computes nor
    declares as sources: what ``dyknow kpl check --recording`` takes as existing.
    """
    computed, spec_sources = _spec_labels(program)
    return [x for x in recorded if x not in computed and x not in spec_sources]


def _local_labels(labels: list[str], mapping: LabelMapping) -> dict[str, str]:
    """The recorded labels the mapping turns into local ones (the others stay as they are)."""
    from ontology import OntologyError

    out: dict[str, str] = {}
    for label in labels:
        try:
            out[label] = mapping.to_local(label)
        except (OntologyError, ValueError, KeyError):
            continue  # not a semantic label of this platform: replayed under its own name
    return out


async def run_replay(
    path: Path,
    *,
    kpl: Path | None,
    prints: list[str] | None,
    speed: float | None,
    tail: float,
    emit: Callable[[str, Any, int, int], None],
    warn: Say,
    mapping: LabelMapping | None = None,
) -> dict[str, Any]:
    """Replay ``path`` into a fresh manual-clock instance; the summary (JSON-ready).

    With ``kpl`` the spec is set up first: recorded labels it declares as sources are fed
    by the recording, recorded labels it does not declare become sources, and recorded
    labels it computes are not fed (it recomputes them). ``emit`` gets every sample of
    the printed labels (default: with a spec every stream not fed by the recording,
    without one the recorded labels) as it is produced. With ``mapping`` (a node's), the
    recorded semantic labels it maps are replayed under their local labels, as the
    node's KPL names them.
    """
    opened = open_recording(path)
    data = opened.info()  # one pass for the labels and the first available time
    for topic, n in data["undecodable"].items():
        warn(f"dyknow replay: {topic}: {n} messages not decoded ({data['problems'][topic]})")
    rename = {} if mapping is None else _local_labels(list(data["counts"]), mapping)
    rec: Recording | RosbagRecording | _Renamed = _Renamed(opened, rename) if rename else opened
    recorded = [rename.get(label, label) for label in data["counts"]]
    start = opened.header.start
    if data["available_span"] is not None:
        start = min(start, data["available_span"][0])
    program = _read_spec(kpl) if kpl is not None else None
    computed, spec_sources = _spec_labels(program) if program is not None else (set(), set())
    feed = [label for label in recorded if label not in computed]
    inst = DyKnowInstance("replay", clock=ManualClock(start))
    async with inst:
        for label in feed:
            if label not in spec_sources:
                inst.add_source(label)
        if program is not None:
            if kpl is not None and str(Path.cwd()) not in sys.path:
                # a spec's CUs name modules as ``python -m`` would find them from here
                sys.path.insert(0, str(Path.cwd()))
            if kpl is not None and mapping is not None and str(kpl.parent) not in sys.path:
                # a node's application: its CUs import from beside it, as the node has them
                sys.path.insert(0, str(kpl.parent))
            try:
                setup_kpl(inst, program)
            except KPLCheckError as exc:
                raise ReplayUsageError("\n".join(e.format(str(kpl)) for e in exc.errors)) from None
            except KPLSetupError as exc:
                raise ReplayUsageError(f"{kpl}:{exc.line}:{exc.column}: {exc.message}") from None
        missing = sorted(spec_sources - set(recorded))
        for label in missing:
            warn(f"dyknow replay: spec source {label!r} is not in the recording: nothing feeds it")
        if missing and mapping is None and recorded:
            warn(
                f"dyknow replay: the recording's labels are {', '.join(recorded)}; a node's KPL "
                "names its local labels: give the node's config (--config NODE.toml) to "
                "replay the recording's semantic labels under its mapping's local ones"
            )
        if prints is None:
            shown = [x for x in inst.labels() if x not in feed] if program else recorded
        else:
            unknown = [x for x in prints if not inst.has_label(x)]
            if unknown:
                raise ReplayUsageError(
                    f"dyknow replay: --print {unknown[0]!r}: no such stream "
                    f"(streams: {', '.join(inst.labels())})"
                )
            shown = list(dict.fromkeys(prints))
        produced = dict.fromkeys(shown, 0)
        for label in shown:
            inst.subscribe(label, callback=_printer(label, produced, emit))
        summary = await replay(rec, inst, speed=speed, labels=feed, tail=tail)
        failures = [f"{f.process}: {f.error}" for f in inst.failures]
    result = summary.as_dict()
    result.update(
        file=str(path),
        produced=produced,
        not_fed={k: v for k, v in summary.skipped.items() if k in computed},
        undecodable=data["undecodable"],
        failures=failures,
    )
    return result


def _printer(
    label: str, produced: dict[str, int], emit: Callable[[str, Any, int, int], None]
) -> Callable[[list[Any]], None]:
    def on_batch(batch: list[Any]) -> None:
        for value, tv, ta in batch:
            produced[label] += 1
            emit(label, value, tv, ta)

    return on_batch


def summary_lines(result: dict[str, Any]) -> list[str]:
    """The end-of-replay summary as text."""
    lines = [f"replayed {result['samples']} samples from {result['file']}"]
    for label, n in result["counts"].items():
        lines.append(f"  {label}: {n}")
    for label, n in result["not_fed"].items():
        lines.append(f"  {label}: {n} recorded, not fed (the spec computes it)")
    if result["valid_span"] is not None:
        lo, hi = result["valid_span"]
        lines.append(f"valid time {_span(lo, hi)}")
    produced = ", ".join(f"{k}={n}" for k, n in result["produced"].items())
    lines.append(f"printed: {produced or '-'}")
    for topic, n in result["undecodable"].items():
        lines.append(f"  {topic}: {n} messages not decoded, not replayed")
    if result["truncated"]:
        lines.append("the recording is truncated: replayed up to its last complete chunk")
    for f in result["failures"]:
        lines.append(f"process failure: {f}")
    return lines


def print_sample(as_json: bool, say: Say) -> Callable[[str, Any, int, int], None]:
    """The ``emit`` of ``run_replay`` for the CLI: a line per produced sample."""

    def emit(label: str, value: Any, valid: int, available: int) -> None:
        if as_json:
            row = {"label": label, "value": jsonable(value), "valid": valid, "available": available}
            say(json.dumps(row, sort_keys=True))
        else:
            say(f"{label}  valid={when_ns(valid)}  available={when_ns(available)}  {value!r}")

    return emit


def check_speed(speed: float | None) -> float | None:
    """Check ``--speed`` (None: as fast as possible)."""
    if speed is not None and not (speed > 0 and speed < float("inf")):
        raise ReplayUsageError(f"dyknow replay: --speed must be > 0, got {speed}")
    return speed


__all__ = [
    "ReplayUsageError",
    "check_speed",
    "info",
    "info_lines",
    "jsonable",
    "load_mapping",
    "open_recording",
    "print_sample",
    "record_federation",
    "run_replay",
    "summary_lines",
]
