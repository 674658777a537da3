"""What the Gateway Agent does with a request's content: the ACL face of a DyKnow instance.

Kept apart from the agent so the mapping (JSON content ↔ core calls) is plain functions,
which the Federation Agent uses too. It lives in `federation`, not `agents`: `agents`
knows nothing of DyKnow.

Content is JSON (language ``json``, ontology ``dyknow``). Times are seconds at this
edge: absolute on the instance's time line, or relative to the provider's now when the
request says ``"relative": true`` (``from: -120`` = the last two minutes).
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import contextlib
from collections.abc import Iterable, Iterator, Sequence
from enum import Enum
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from agents import platform_of
from dyknow_core import (
    NS_PER_S,
    Answer,
    Approximation,
    ComputationalUnit,
    DyKnowError,
    DyKnowInstance,
    Policy,
    PolicyError,
    Process,
    ProcessError,
    RawSample,
    UnknownLabelError,
    ns_to_seconds,
    seconds_to_ns,
)

from ._batch import check_semantic_label

ONTOLOGY = "dyknow"

# Seconds at the edge, finite and bounded: seconds_to_ns(1e300) overflows (the bound is
# ±31 700 years, far beyond any time line).
Seconds = Annotated[float, Field(allow_inf_nan=False, ge=-1e12, le=1e12)]
# Another platform may not ask for a grid finer than 1 ms: a gap in the data would make
# each sample fill (up to a buffer of) grid points in the provider's publishing call.
MIN_REMOTE_PERIOD = 1e-3
RemotePeriod = Annotated[float, Field(allow_inf_nan=False, ge=MIN_REMOTE_PERIOD, le=1e9)]


class GatewayRefusal(Exception):
    """A request the gateway will not perform; ``reason`` goes into the refuse."""

    def __init__(self, reason: str, code: str | None = None) -> None:
        self.reason = reason
        self.code = code  # set: a refusal the agent counts and audits under this code
        super().__init__(reason)


class _Content(BaseModel):
    # defer_build: a kind of request is built when the first one arrives, not at start
    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)


class ListLabels(_Content):
    """``{"action": "list-labels", "pattern": "car/*"}`` → ``{"labels": [...]}``."""

    action: Literal["list-labels"]
    pattern: str | None = None


class PolicySpec(_Content):
    """A policy as it travels in ACL content: seconds everywhere, start/end maybe relative."""

    start: Seconds | None = Field(default=None, alias="from")
    end: Seconds | None = Field(default=None, alias="to")
    relative: bool = False
    sample_period: RemotePeriod | None = None
    approximation: str = "none"
    max_delay: Seconds | None = None
    late: str = "drop"
    order: str = "any"
    change: Any = "any_update"
    lower: float | None = None
    upper: float | None = None
    buffer_size: int = 4096
    overflow: str = "drop_oldest"

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    def to_policy(self, now: int) -> Policy:
        """The core policy, with start/end on the instance's nanosecond time line."""
        base = now if self.relative else 0

        def at(t: float | None) -> int | None:
            return None if t is None else base + seconds_to_ns(t)

        return Policy(
            start=at(self.start),
            end=at(self.end),
            sample_period=self.sample_period,
            approximation=self.approximation,
            max_delay=self.max_delay,
            late=self.late,
            order=self.order,
            change=self.change,
            lower=self.lower,
            upper=self.upper,
            buffer_size=self.buffer_size,
            overflow=self.overflow,
        )


class Query(_Content):
    """A query for one label: ``latest``, value ``at`` t, or all ``between`` from and to."""

    action: Literal["query"]
    label: str
    kind: Literal["latest", "at", "between"] = "latest"
    t: Seconds | None = None
    start: Seconds | None = Field(default=None, alias="from")
    end: Seconds | None = Field(default=None, alias="to")
    relative: bool = False
    as_of: Seconds | None = None
    approximation: Literal["most_recent", "closest", "linear"] = "most_recent"

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)


class CreateStream(_Content):
    """Publish ``output``: the stream ``label`` seen through ``policy`` (a new stream generator)."""

    action: Literal["create-stream"]
    label: str
    output: str
    # constructed, not validated: the default is PolicySpec(), and its validator is built
    # when the first request that carries a policy arrives, not at every platform's start
    policy: PolicySpec = PolicySpec.model_construct()


class RemoveStream(_Content):
    """End the stream a create-stream published as ``label`` (its creator's platform or
    this platform's agents only): ``{"removed": label}``, or ``{"kept": label}`` when a
    process here reads it (handed to this platform, the slot freed all the same)."""

    action: Literal["remove-stream"]
    label: str


class Subscribe(_Content):
    """Content of a FIPA-Subscribe: the label and the policy its informs follow."""

    label: str
    policy: PolicySpec = PolicySpec.model_construct()  # as CreateStream's


_SCALARS = (str, int, float, bool, type(None))


def jsonable(value: Any) -> Any:
    """A sample value as a JSON value: tuples (positions) and named tuples (events) included.

    ACL content is JSON, which has no tuples; a value that is no JSON at all becomes its
    text rather than failing the whole answer.
    """
    if isinstance(value, _SCALARS):
        return value
    if isinstance(value, Enum):
        return jsonable(value.value)
    if isinstance(value, tuple) and hasattr(value, "_asdict"):
        return {k: jsonable(v) for k, v in value._asdict().items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [jsonable(v) for v in value]
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    return str(value)


_SCALAR_TYPES = frozenset(_SCALARS)


def answer_to_json(answer: Answer) -> dict[str, Any]:
    """A query answer as content: samples as [value, valid s, available s]."""
    return {"label": answer.label, **answer_content(answer)}


def answer_content(answer: Answer) -> dict[str, Any]:
    """`answer_to_json` without the label: what the Federation Agent answers per label."""
    scalar = _SCALAR_TYPES
    return {
        "query_time": ns_to_seconds(answer.query_time),
        "samples": [
            # a plain scalar as it is, without a call (what jsonable returns for it)
            [
                value if type(value) in scalar else jsonable(value),
                valid / NS_PER_S,  # as ns_to_seconds, inline
                available / NS_PER_S,
            ]
            for value, valid, available in answer.samples
        ],
    }


def latest_contents(instance: DyKnowInstance, labels: Sequence[str]) -> list[dict[str, Any]]:
    """`answer_content` of ``instance.latest(label)`` for each of ``labels``, at one clock reading.

    What a provider answers to a get-latest of many labels, without an `Answer` per label
    (`DyKnowInstance.latest_many`); an unknown label raises as `latest` does.
    """
    return latest_contents_plain(instance, labels)[0]


def latest_contents_plain(
    instance: DyKnowInstance, labels: Sequence[str]
) -> tuple[list[dict[str, Any]], bool]:
    """`latest_contents`, and whether they are plain JSON values.

    Plain: every value and time in them a str, int, float, bool or None of exactly that
    type (told as each label's content is made), so that an answer made of them may be
    handed over to its reply without a copy (`agents.HandedOver`).
    """
    now, rows = instance.latest_many(labels)
    return contents_plain(now, rows)


def contents_plain(now: int, rows: Sequence[RawSample | None]) -> tuple[list[dict[str, Any]], bool]:
    """`latest_contents_plain` of the rows `DyKnowInstance.latest_many` read at ``now``."""
    ns = NS_PER_S
    query_time = now / ns  # as ns_to_seconds, inline
    scalar = _SCALAR_TYPES
    plain = type(query_time) is float
    out: list[dict[str, Any]] = []
    add = out.append
    # one pass over the rows (a call per label per pass is most of this function's cost)
    for s in rows:
        if s is None:
            add({"query_time": query_time, "samples": []})
            continue
        value = s[0]
        valid = s[1] / ns
        available = s[2] / ns
        if type(value) not in scalar:  # what jsonable makes of it
            value = jsonable(value)
            plain = False
        elif plain and (type(valid) not in scalar or type(available) not in scalar):
            plain = False
        add({"query_time": query_time, "samples": [[value, valid, available]]})
    return out, plain


def latest_answer_plain(label: str, now: int, s: RawSample | None) -> tuple[dict[str, Any], bool]:
    """`answer_to_json` of ``label``'s latest sample ``s`` read at ``now``, and whether it is
    plain JSON (`contents_plain` of that one row, with the label first)."""
    query_time = now / NS_PER_S  # as ns_to_seconds, inline
    if s is None:
        return {"label": label, "query_time": query_time, "samples": []}, (
            type(query_time) is float
        )
    scalar = _SCALAR_TYPES
    value = s[0]
    valid = s[1] / NS_PER_S
    available = s[2] / NS_PER_S
    if type(value) not in scalar:  # what jsonable makes of it
        value = jsonable(value)
        plain = False
    else:
        plain = type(query_time) is float and type(valid) in scalar and type(available) in scalar
    return {"label": label, "query_time": query_time, "samples": [[value, valid, available]]}, plain


def samples_to_json(batch: list[tuple[Any, int, int]]) -> list[list[Any]]:
    """Raw samples as content rows: [value, valid s, available s]."""
    return [[jsonable(v), ns_to_seconds(tv), ns_to_seconds(ta)] for v, tv, ta in batch]


_LATEST_KEYS = frozenset({"action", "label", "kind"})


def plain_latest(content: Any) -> str | None:
    """The label of a plain query for the latest sample, ``{"action": "query", "label": …}``.

    What `Query` accepts of that shape (``kind`` absent or ``"latest"``, nothing else),
    checked in plain Python; None for anything else, which `GatewayService.parse` decides.
    """
    if type(content) is not dict or not content.keys() <= _LATEST_KEYS:
        return None
    label = content.get("label")
    kind = content.get("kind", "latest")
    action = content.get("action")
    if (
        type(label) is str
        and type(kind) is str
        and kind == "latest"
        and type(action) is str
        and action == "query"
    ):
        return label
    return None


class GatewayService:
    """Performs gateway requests on one DyKnow instance; refusals carry a reason.

    At most ``max_streams`` streams created at once, whoever asked, and at most
    ``max_streams_per_platform`` of them asked by one other platform (a create-stream
    that says it is ``limited``): one member cannot take every slot from the others.
    """

    def __init__(
        self,
        instance: DyKnowInstance,
        *,
        max_streams: int = 256,
        max_streams_per_platform: int = 64,
    ) -> None:
        check_limits(max_streams=max_streams, max_streams_per_platform=max_streams_per_platform)
        self.instance = instance
        self.max_streams = max_streams
        self.max_streams_per_platform = max_streams_per_platform
        self.created: dict[str, str] = {}  # output label -> process name
        # output label -> the agent that asked for it: kept and freed with `created`, so
        # what one platform holds is counted from it and cannot drift from the streams; a
        # stream the program created by calling the service (no asker) has none: a reload
        # or a revocation leaves it, as one of this platform's own agents
        self.creators: dict[str, str] = {}
        # the unit each create-stream added: a process of that name that is another one
        # (this one removed by hand, the name reused) is not the gateway's to remove
        self._units: dict[str, ComputationalUnit] = {}

    def parse(self, content: Any) -> ListLabels | Query | CreateStream | RemoveStream:
        """Validate request content; GatewayRefusal names what is wrong."""
        if not isinstance(content, dict) or not isinstance(content.get("action"), str):
            raise GatewayRefusal("content must be a JSON object with an 'action'")
        kinds: dict[str, type[ListLabels | Query | CreateStream | RemoveStream]] = {
            "list-labels": ListLabels,
            "query": Query,
            "create-stream": CreateStream,
            "remove-stream": RemoveStream,
        }
        model = kinds.get(content["action"])
        if model is None:
            raise GatewayRefusal(
                f"unknown action {content['action']!r} (known: {', '.join(sorted(kinds))})"
            )
        with _refused_if_invalid():
            return model.model_validate(content)

    def perform(self, content: Any, asker: str = "", *, limited: bool = False) -> dict[str, Any]:
        """Do what the content asks; the inform's content, or GatewayRefusal.

        ``asker`` is the agent asking (a stream it creates is recorded as its; none:
        the program itself, this platform's);
        ``limited``: its platform is bound by ``max_streams_per_platform`` (another one).
        """
        label = plain_latest(content)
        if label is not None:
            # the common request, done as `query` does it without its model (pydantic's
            # validation costs more than the query); anything else, errors included,
            # goes through `parse`, which says what is wrong
            try:
                return answer_to_json(self.instance.latest(label))
            except UnknownLabelError as exc:
                raise GatewayRefusal(str(exc), code="unknown-label") from exc
            except DyKnowError as exc:
                raise GatewayRefusal(str(exc)) from exc
        req = self.parse(content)
        try:
            if isinstance(req, ListLabels):
                return {"labels": self.instance.labels(req.pattern)}
            if isinstance(req, Query):
                return answer_to_json(self.query(req))
            if isinstance(req, RemoveStream):
                return self.remove_stream(req, asker, limited=limited)
            return self.create_stream(req, asker, limited=limited)
        except UnknownLabelError as exc:
            raise GatewayRefusal(str(exc), code="unknown-label") from exc
        except DyKnowError as exc:
            raise GatewayRefusal(str(exc)) from exc

    def _time(self, t: float | None, relative: bool, now: int) -> int | None:
        if t is None:
            return None
        return (now if relative else 0) + seconds_to_ns(t)

    def query(self, q: Query) -> Answer:
        """Run a latest / at / between query on the instance."""
        dk = self.instance
        now = dk.clock.now()
        as_of = self._time(q.as_of, q.relative, now)
        if q.kind == "latest":
            return dk.latest(q.label, as_of=as_of)
        if q.kind == "at":
            t = self._time(q.t, q.relative, now)
            if t is None:
                raise GatewayRefusal("a query 'at' needs 't'")
            return dk.at(q.label, t, approximation=Approximation(q.approximation), as_of=as_of)
        t1 = self._time(q.start, q.relative, now)
        t2 = self._time(q.end, q.relative, now)
        return dk.between(
            q.label,
            -(2**62) if t1 is None else t1,
            now if t2 is None else t2,
            as_of=as_of,
        )

    def create_stream(
        self, req: CreateStream, asker: str = "", *, limited: bool = False
    ) -> dict[str, Any]:
        """Publish ``req.output`` as ``req.label`` filtered by the policy, for ``asker``
        (``limited``: within its platform's ``max_streams_per_platform`` too)."""
        dk = self.instance
        self._forget_removed()  # a stream removed by hand frees its slot
        if limited:
            platform = platform_of(asker)
            if self.held_by(platform) >= self.max_streams_per_platform:
                raise GatewayRefusal(
                    f"too many created streams for {platform} "
                    f"(limit {self.max_streams_per_platform} per platform)",
                    code="stream-limit",
                )
        if len(self.created) >= self.max_streams:
            raise GatewayRefusal(
                f"too many created streams (limit {self.max_streams})", code="stream-limit"
            )
        try:
            check_semantic_label(req.output)
        except ValueError as exc:
            raise GatewayRefusal(f"output: {exc}", code="bad-label") from exc
        if dk.has_label(req.output):
            # another platform could learn this way which labels exist: counted and
            # audited as asking a label not here is
            raise GatewayRefusal(f"label {req.output!r} is already published", code="label-taken")
        policy = req.policy.to_policy(dk.clock.now())
        name = f"gateway:{req.output}"
        cu = dk.add_cu(name, _identity, [(req.label, policy)], req.output)
        self.created[req.output] = name
        self._units[req.output] = cu
        if asker:  # none: the program called the service itself, for its own platform
            self.creators[req.output] = asker
        return {"label": req.output, "source": req.label}

    def remove_stream(
        self, req: RemoveStream, asker: str = "", *, limited: bool = False
    ) -> dict[str, Any]:
        """End the stream created as ``req.label`` for ``asker`` (``limited``: another
        platform's, which may end only those its own agents created), as its process
        removed by hand; one a process staying here reads is kept, handed to this
        platform. Either way its creator's slot is free at once."""
        dk = self.instance
        label = req.label
        self._forget_removed()  # one removed by hand is no created stream any more
        if label not in self.created:
            if not dk.has_label(label):
                raise UnknownLabelError(label, dk.labels())
            raise GatewayRefusal(
                f"stream {label!r} was not created by a create-stream", code="not-created"
            )
        creator = self.creators.get(label, "")
        if limited:
            platform = platform_of(asker)
            if not creator or platform_of(creator) != platform:
                raise GatewayRefusal(
                    f"stream {label!r} was not created by {platform}", code="not-creator"
                )
        if self.read_on([label]):
            # as a reload keeps it: what is built on it here keeps its input
            self.creators.pop(label, None)
            return {"kept": label}
        self.remove(label)
        return {"removed": label}

    def held_by(self, platform: str) -> int:
        """How many of the streams created here ``platform``'s agents asked for (one
        removed by hand since no more)."""
        self._forget_removed()
        return sum(1 for a in self.creators.values() if platform_of(a) == platform)

    def _is_ours(self, output: str) -> bool:
        name = self.created.get(output)
        unit = self._units.get(output)
        return name is not None and unit is not None and self.instance.processes.get(name) is unit

    def _forget_removed(self) -> None:
        for output in [o for o in self.created if not self._is_ours(o)]:
            del self.created[output]
            self._units.pop(output, None)
            self.creators.pop(output, None)

    def remove(self, output: str) -> bool:
        """Remove the stream created as ``output`` (its process, which closes the label);
        False when there is none (never created here, or its process is gone already or
        the name now another process's: that one stays)."""
        ours = self._is_ours(output)
        name = self.created.pop(output, None)
        self._units.pop(output, None)
        self.creators.pop(output, None)
        if name is None or not ours:
            return False
        try:
            self.instance.remove_process(name)
        except ProcessError:
            return False
        return True

    def read_on(self, outputs: Iterable[str]) -> dict[str, list[str]]:
        """Of the created streams ``outputs`` about to be removed, those a process that
        stays reads as input (one of the instance's, the application's included, not
        itself among those removed): output -> the names of the processes reading it."""
        going = {o for o in outputs if self._is_ours(o)}
        kept: dict[str, list[str]] = {}
        changed = True
        while changed:  # a stream kept keeps what it reads in turn
            changed = False
            leaving = {self.created[o] for o in going}
            for proc in self.instance.processes.values():
                if proc.name in leaving:
                    continue
                for label in _inputs_of(proc) & going:
                    kept.setdefault(label, []).append(proc.name)
                    going.discard(label)
                    changed = True
        return kept

    def subscription_policy(self, content: Any) -> tuple[str, Policy]:
        """Validate FIPA-Subscribe content into (label, policy)."""
        with _refused_if_invalid():
            sub = Subscribe.model_validate(content)
            policy = sub.policy.to_policy(self.instance.clock.now())
        if not self.instance.has_label(sub.label):
            unknown = UnknownLabelError(sub.label, self.instance.labels())
            raise GatewayRefusal(str(unknown), code="unknown-label") from unknown
        return sub.label, policy


def check_limits(**limits: int) -> None:
    """Raise ValueError naming the first of ``limits`` that is no count (an int, at least 0)."""
    for key, value in limits.items():
        if type(value) is not int or value < 0:
            raise ValueError(f"{key}: must be a whole number of at least 0, not {value!r}")


@contextlib.contextmanager
def _refused_if_invalid() -> Iterator[None]:
    """Content that does not validate, or a policy that cannot be, as a GatewayRefusal."""
    try:
        yield
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err.get("loc", ())) or "content"
        raise GatewayRefusal(f"field {where!r}: {err.get('msg', 'invalid')}") from exc
    except PolicyError as exc:
        raise GatewayRefusal(str(exc)) from exc


def _inputs_of(proc: Process) -> set[str]:
    """The labels a process reads, as its description names them (each kind its key)."""
    d = proc.describe()
    labels: set[str] = set()
    for key in ("inputs", "components"):
        value = d.get(key)
        if isinstance(value, dict):
            value = list(value.values())
        if isinstance(value, list):
            labels.update(v for v in value if isinstance(v, str))
    for key in ("source", "local", "imported", "target"):
        value = d.get(key)
        if isinstance(value, str):
            labels.add(value)
    return labels


def _identity(v: Any) -> Any:
    """The function of a created stream: its policy does the work."""
    return v
