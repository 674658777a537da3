"""One platform of a DyKnow Federation, assembled from a config file.

`FederationPlatform` builds, from a `PlatformConfig`: the DyKnow instance (or takes one),
the transport (zenoh or MQTT), the agent platform with its Interface Agent (keys and the
federation's trust file), the Gateway Agent, the export and import proxies, and the
DyKnow Federation Agent (which translates with the platform's label mapping, searches
labels by formula, and starts exports through the export proxy). Leaving the context
tears everything down in reverse.

Imported streams land in local labels named by the config's ``import_label`` scheme
(default ``import/{sender}/{semantic}``); only labels of the federation's vocabulary are
accepted, anything else is dropped and counted by the import proxy.

A config file (TOML; relative paths are relative to the file)::

    name = "uav-b"
    federation = "traffic"
    key = "keys/uav-b.key"
    trust = "trust.json"
    vocabulary = "traffic.toml"
    mapping = "uav-b.toml"
    export_limit = 64
    export_limit_per_platform = 32   # exports one other platform may hold here
    history_limit_per_platform = 200000  # samples of history kept for one other platform
    export_lease = 10.0
    import_label = "import/{sender}/{semantic}"

    [security]                   # docs/security.md; these are the defaults
    encrypt = true               # ChaCha20-Poly1305 bodies; false: MAC only (debugging)
    require_encryption = true    # refuse plain envelopes (default: the same as encrypt)
    audit = "sealed"             # published audit sealed to the owner; "plain" or "off"
    watch = true                 # the owner may watch what arrives (dyknow watch)

    [[facts]]                    # label search by formula (docs/ontology.md): (Car car5)
    predicate = "Car"
    stream = "car/{object}/state"
    unary = true

    [sharing]                    # what is shared with whom (federation/_sharing.py)
    gateway = "private"          # "protected": other members may use the Gateway Agent
    default = "members"          # labels no rule names: every member, or "none"
    accept_for = ["operator"]    # whose create-stream may direct streams here

    [[sharing.rules]]
    name = "neighbours"
    labels = ["car*-state"]
    query = ["uav-*"]
    stream = ["uav-a", "uav-c"]

    [rate_limit]                 # per other platform, after authentication (docs/security.md)
    rate = 5000.0                # requests/queries/cfps per second, bursts of `burst`
    burst = 200.0

    [console]                    # `dyknow console` only (docs/console.md)
    streams = ["heli-position", "violation"]   # asked of every other member
    allow_hosts = ["operator.example.org"]
    token_file = "console.token"

    [console.roles]              # how the console's page draws them
    positions = "heli-position"
    violations = ["violation"]   # a label, or a list of them (all listed as violations)

    [foxglove]                   # `dyknow foxglove` only (docs/foxglove.md)
    origin = [58.3975, 15.5765]  # latitude, longitude of x = y = 0
    streams = ["heli-position"]  # default: console.streams (roles: console.roles)
    local = ["operator/observations"]  # labels of this platform's own instance, served too
    origins = ["https://app.foxglove.dev", "file://"]  # web pages let in (the default)
    allow_hosts = ["viewer.example.org"]  # default: console.allow_hosts
    token_file = "foxglove.token"         # default: console.token_file

    [transport]
    kind = "zenoh"
    mode = "peer"
    listen = ["tcp/127.0.0.1:7448"]
    connect = ["tcp/127.0.0.1:7447"]
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import asyncio
import contextlib
import fnmatch
import inspect
import logging
import os
import re
import stat
import string
import tomllib
from collections.abc import Awaitable, Callable, Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, Self, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from agents import (
    AgentError,
    AgentPlatform,
    AuditLog,
    DfEventLimit,
    InterfaceAgent,
    KeyPair,
    KxLimit,
    RateLimit,
    SecurityError,
    SecurityPolicy,
    TrustStore,
    Visibility,
    call_in_loop,
    platform_of,
)
from agents.transports import (
    MqttConfig,
    Presence,
    Subscription,
    Transport,
    ZenohConfig,
    ZenohTransport,
)
from dyknow_core import DyKnowInstance, Source
from ontology import (
    FactBase,
    FactFeed,
    LabelMapping,
    OntologyError,
    PlatformLabels,
    Rule,
    StreamRule,
    Vocabulary,
)

from ._export import ExportProxy
from ._fusion import Fusion, add_fusion
from ._gateway import GatewayAgent, GatewayEnded, _gateway_told
from ._geo import check_origin
from ._import import Import, ImportProxy
from ._inputs import InputSettings
from ._outputs import OutputSettings
from ._service import UNSHARED_WHY, Anchor, Denied, FederationAgent, MembershipEvent
from ._sessions import InterfaceSessions
from ._sharing import SharingRule, SharingSettings, _no_items

__all__ = [
    "DEFAULT_IMPORT_LABEL",
    "ConsoleRoles",
    "ConsoleSettings",
    "DfEventLimitSettings",
    "FactSettings",
    "FederationPlatform",
    "FoxgloveSettings",
    "KxLimitSettings",
    "MqttSettings",
    "PlatformConfig",
    "PlatformConfigError",
    "RateLimitSettings",
    "SecuritySettings",
    "SharingSettings",
    "ZenohSettings",
    "load_sharing",
    "sharing_changes",
]

log = logging.getLogger(__name__)

DEFAULT_IMPORT_LABEL = "import/{sender}/{semantic}"
"""Where a stream imported from ``sender`` lands, by default."""

_NAME = r"^[A-Za-z0-9_.-]+$"
_IMPORT_FIELDS = frozenset({"sender", "semantic"})
_KINDS = frozenset({"zenoh", "mqtt", "file", "python", "ros2", "rosbag"})  # of inputs/outputs

OnImportEnded = Callable[[str, list[str]], Awaitable[None] | None]
"""``on_import_ended(sender, semantic_labels)``: the streams imported from a gone sender ended."""


class PlatformConfigError(ValueError):
    """A platform's configuration is wrong: names the source (file) and the key."""

    def __init__(self, source: str, key: str | None, message: str) -> None:
        self.source = source
        self.key = key
        self.message = message
        super().__init__(f"{source}: {key}: {message}" if key else f"{source}: {message}")


# -- the config ------------------------------------------------------------------------------

# every table of the file: a limit of inf (or nan) is a number TOML reads, and none of ours
# means anything with it; refused here, naming file, table and key, not at start-up
_SETTINGS = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
# a table of PlatformConfig's: its checks are part of PlatformConfig's validator, and a table
# left out is its defaults, constructed (what validating nothing gives); its own validator is
# built only if something validates the table alone
_TABLE = ConfigDict(**_SETTINGS, defer_build=True)


class ZenohSettings(ZenohConfig):
    """The ``[transport]`` table for zenoh (``kind = "zenoh"``): mode, listen, connect, …."""

    model_config = ConfigDict(allow_inf_nan=False)  # merged with ZenohConfig's

    kind: Literal["zenoh"] = "zenoh"


class MqttSettings(MqttConfig):
    """The ``[transport]`` table for MQTT (``kind = "mqtt"``): host, port, keepalive, …."""

    model_config = ConfigDict(allow_inf_nan=False)  # merged with MqttConfig's

    kind: Literal["mqtt"] = "mqtt"


TransportSettings = Annotated[ZenohSettings | MqttSettings, Field(discriminator="kind")]


_LIMIT = RateLimit()  # the defaults
_Limit = TypeVar("_Limit", RateLimit, KxLimit, DfEventLimit)


class _LimitSettings(BaseModel):
    """A limit's table: ``enabled`` and the keyword arguments of the limit it builds."""

    model_config = _TABLE

    enabled: bool = True

    def _limit(self, kind: type[_Limit]) -> _Limit | None:
        """The ``kind`` these settings describe, or None when disabled."""
        if not self.enabled:
            return None
        # its fields as they are (numbers): a dump would build the table's serializer
        fields = type(self).model_fields
        return kind(**{name: getattr(self, name) for name in fields if name != "enabled"})


class RateLimitSettings(_LimitSettings):
    """The ``[rate_limit]`` table: what each other platform may send here (`RateLimit`)."""

    rate: float = Field(default=_LIMIT.rate, gt=0)
    burst: float = Field(default=_LIMIT.burst, ge=1)
    total_rate: float = Field(default=_LIMIT.total_rate, gt=0)
    total_burst: float = Field(default=_LIMIT.total_burst, ge=1)
    refusals: float = Field(default=_LIMIT.refusals, ge=0)
    report_interval: float = Field(default=_LIMIT.report_interval, gt=0)
    unauthenticated: float = Field(default=_LIMIT.unauthenticated, ge=0)

    def to_rate_limit(self) -> RateLimit | None:
        """The Interface Agent's limit, or None when disabled."""
        return self._limit(RateLimit)


class ConsoleRoles(BaseModel):
    """``[console.roles]``: which streamed label the console's page draws as what.

    Each is one of ``streams`` or unset (nothing drawn so): ``positions`` a member's
    position ``{"x", "y", "z"}``, ``areas`` the area it covers ``{"polygon", "index",
    "delegated-by"}``, ``tracks`` what it tracks ``{"cars": [{"id", "x", "y", …}]}``,
    ``violations`` one event per sample (listed, and drawn at its ``x``, ``y``): one label
    or a list of them (a platform may publish each kind of violation on its own), all
    listed together.
    """

    model_config = _TABLE

    positions: str | None = None
    areas: str | None = None
    tracks: str | None = None
    violations: str | tuple[Annotated[str, Field(min_length=1)], ...] | None = None

    def assigned(self) -> list[tuple[str, str]]:
        """Every ``(role, label)`` set; a role with a list of labels once per label."""
        pairs: list[tuple[str, str]] = []
        for role, value in self.model_dump().items():
            labels = () if value is None else (value,) if isinstance(value, str) else value
            pairs.extend((role, label) for label in labels)
        return pairs

    def among(self, streams: tuple[str, ...]) -> "ConsoleRoles":
        """These roles with only the labels among ``streams`` (a role left without unset)."""
        update: dict[str, Any] = {}
        for role, value in self.model_dump().items():
            if isinstance(value, str) and value not in streams:
                update[role] = None
            elif isinstance(value, tuple) and any(label not in streams for label in value):
                kept = tuple(label for label in value if label in streams)
                update[role] = kept or None
        return self.model_copy(update=update)


def _each_once(labels: tuple[str, ...]) -> None:
    """ValueError naming a label a settings list (``streams``) holds twice (the first sorted)."""
    twice = sorted({label for label in labels if labels.count(label) > 1})
    if twice:
        raise ValueError(f"{twice[0]!r} is listed twice")


class ConsoleSettings(BaseModel):
    """``[console]``: what the operator console streams and who may use it (docs/console.md).

    ``streams`` are the semantic labels the console asks every other member for, ``roles``
    how its page draws them (`ConsoleRoles`); a stream with no role is listed with its
    latest value. ``allow_hosts`` are host names a request's ``Host`` may name besides
    localhost and IP addresses; ``token_file`` holds the console's token (else
    ``DYKNOW_CONSOLE_TOKEN``, else a random one, printed at start). ``idle_timeout``: the
    seconds a connection has to send a whole request before it is closed;
    ``max_clients_per_address``: the connections one client address may hold open at once
    (of 128 in all; behind a shared proxy every client has the proxy's address).
    """

    model_config = _TABLE

    streams: tuple[Annotated[str, Field(min_length=1)], ...] = ()
    roles: ConsoleRoles = Field(default_factory=ConsoleRoles.model_construct)
    allow_hosts: tuple[str, ...] = ()
    token_file: Path | None = None
    idle_timeout: float = Field(default=15.0, gt=0.0, le=3600.0)
    max_clients_per_address: int = Field(default=32, ge=1, le=128)

    @field_validator("streams")
    @classmethod
    def _distinct(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        _each_once(value)
        return value

    @field_validator("roles")
    @classmethod
    def _roles_are_streams(cls, value: ConsoleRoles, info: ValidationInfo) -> ConsoleRoles:
        streams = info.data.get("streams")
        if streams is None:  # streams was wrong itself: that is the error to name
            return value
        for role, label in value.assigned():
            if label not in streams:
                raise ValueError(
                    f"{role} = {label!r} is not one of streams ({', '.join(streams) or 'none'})"
                )
        return value


FOXGLOVE_ORIGINS = ("https://app.foxglove.dev", "file://")
"""The ``Origin`` values a Foxglove connection may have by default: the web app's, and
``file://``, what an Electron app's pages (the desktop app) send."""
_WEB_ORIGIN = re.compile(r"[a-z][a-z0-9+.-]*://([a-z0-9.-]+|\[[0-9a-f:.]+\])?(:[0-9]{1,5})?")


class FoxgloveSettings(BaseModel):
    """``[foxglove]``: what ``dyknow foxglove`` serves to Foxglove (docs/foxglove.md).

    ``streams`` (default: the console's) are the semantic labels asked of every other
    member, ``roles`` (default: the console's) which of them are positions, areas, tracks
    and violations (`ConsoleRoles`); ``local`` are labels of this platform's own instance
    served too. ``origin`` is the latitude and longitude of the local frame's (0, 0), x
    metres east and y north: with it, positions become ``foxglove.LocationFix`` and areas,
    tracks and violations GeoJSON, drawn on the Map panel.

    Who may connect is as the console's (a token, the allowed ``Host`` names):
    ``token_file`` and ``allow_hosts`` default to the console's. ``origins`` are the web
    origins a browser's connection may come from (`FOXGLOVE_ORIGINS`: Foxglove's web app
    and an Electron app's ``file://``); one without an ``Origin`` is no browser page.
    """

    model_config = _TABLE

    streams: tuple[Annotated[str, Field(min_length=1)], ...] | None = None
    roles: ConsoleRoles | None = None
    local: tuple[Annotated[str, Field(min_length=1)], ...] = ()
    origin: tuple[float, float] | None = None
    origins: tuple[str, ...] = FOXGLOVE_ORIGINS
    allow_hosts: tuple[str, ...] | None = None
    token_file: Path | None = None

    @field_validator("origins")
    @classmethod
    def _web_origins(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        for origin in value:
            if not _WEB_ORIGIN.fullmatch(origin):
                raise ValueError(
                    f"{origin!r} is not a web origin (scheme://host[:port], lower case, "
                    "no path: https://app.foxglove.dev)"
                )
        return value

    @field_validator("streams", "local")
    @classmethod
    def _distinct(cls, value: tuple[str, ...] | None) -> tuple[str, ...] | None:
        _each_once(value or ())
        return value

    @field_validator("origin")
    @classmethod
    def _on_earth(cls, value: tuple[float, float] | None) -> tuple[float, float] | None:
        return None if value is None else check_origin(*value)

    def resolve(self, console: ConsoleSettings) -> tuple[tuple[str, ...], ConsoleRoles]:
        """The streams and roles served: these settings', else the console's.

        ValueError when a role names a label that is not one of the streams.
        """
        streams = console.streams if self.streams is None else self.streams
        roles = console.roles if self.roles is None else self.roles
        if self.roles is None:  # the console's roles of streams not served here: none
            return streams, roles.among(streams)
        for role, label in roles.assigned():
            if label not in streams:
                raise ValueError(
                    f"foxglove.roles: {role} = {label!r} is not one of the streams "
                    f"({', '.join(streams) or 'none'})"
                )
        return streams, roles


class SecuritySettings(BaseModel):
    """The ``[security]`` table: confidentiality of what this platform sends and publishes.

    ``encrypt`` (default true): envelopes (ACL messages, sample batches, stream reports)
    are sealed with ChaCha20-Poly1305; false sends them MAC-only, readable on the path
    (for debugging with plain tools). ``require_encryption`` (default: as ``encrypt``)
    refuses, counts and audits plain envelopes. ``audit``: the published audit is
    ``"sealed"`` to the platform's owner, ``"plain"`` JSON lines, or ``"off"`` (not
    published). ``watch``: the owner may watch what arrives (``dyknow watch``).
    """

    model_config = _TABLE

    encrypt: bool = True
    require_encryption: bool | None = None
    audit: Literal["sealed", "plain", "off"] = "sealed"
    watch: bool = True

    def to_policy(self) -> SecurityPolicy:
        """The sessions' policy these settings describe."""
        return SecurityPolicy(encrypt=self.encrypt, require_encryption=self.require_encryption)


_KX = KxLimit()  # the defaults


class KxLimitSettings(_LimitSettings):
    """The ``[kx_limit]`` table: key-exchange requests checked per second (`KxLimit`)."""

    per_peer: float = Field(default=_KX.per_peer, ge=0)
    per_peer_burst: float = Field(default=_KX.per_peer_burst, ge=1)
    total: float = Field(default=_KX.total, ge=0)
    total_burst: float = Field(default=_KX.total_burst, ge=1)
    detailed: int = Field(default=_KX.detailed, ge=0)
    report_interval: float = Field(default=_KX.report_interval, gt=0)

    def to_kx_limit(self) -> KxLimit | None:
        """The Interface Agent's key-exchange load shedding, or None when disabled."""
        return self._limit(KxLimit)


_DF = DfEventLimit()  # the defaults


class DfEventLimitSettings(_LimitSettings):
    """The ``[df_event_limit]`` table: directory events checked per second (`DfEventLimit`)."""

    per_platform: float = Field(default=_DF.per_platform, ge=0)
    per_platform_burst: float = Field(default=_DF.per_platform_burst, ge=1)
    total: float = Field(default=_DF.total, ge=0)
    total_burst: float = Field(default=_DF.total_burst, ge=1)
    detailed: int = Field(default=_DF.detailed, ge=0)
    report_interval: float = Field(default=_DF.report_interval, gt=0)

    def to_df_event_limit(self) -> DfEventLimit | None:
        """The global directory's directory-event load shedding, or None when disabled."""
        return self._limit(DfEventLimit)


class _Field:
    """A stream rule's ``convert`` from a config's ``field``: that key of a dict value."""

    # a plain class, not a dataclass: generating a dataclass's methods costs ~0.4 ms of a
    # node's start, each; equal for the same key, as the rules holding it compare
    __slots__ = ("key",)

    def __init__(self, key: str) -> None:
        self.key = key

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Field) and other.key == self.key

    def __hash__(self) -> int:
        return hash(self.key)

    def __call__(self, value: Any) -> Any:
        return value.get(self.key) if isinstance(value, dict) else None


class FactSettings(BaseModel):
    """One ``[[facts]]`` table: a `StreamRule` keeping ``platform.facts`` current.

    ``stream`` is a local label pattern with ``{object}``; each matching stream's latest
    value is the fact ``(predicate object value)``, or with ``field`` that key of a dict
    value, or with ``unary`` ``(predicate object)`` while the value is true
    (`docs/ontology.md`). Domain rules need the domain made first: pass them as
    ``FederationPlatform(rules=…)``.
    """

    model_config = _TABLE

    predicate: str
    stream: str
    field: str | None = None
    unary: bool = False

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.field is not None and self.unary:
            raise ValueError("'field' and 'unary' exclude each other")
        try:
            # the feed checks its rules (pattern, predicate) when made, before any instance use
            FactFeed(None, FactBase(), [self.to_rule()])  # type: ignore[arg-type]
        except OntologyError as exc:
            raise ValueError(str(exc)) from None
        return self

    def to_rule(self) -> StreamRule:
        """The `StreamRule` this table describes."""
        convert = _Field(self.field) if self.field is not None else None
        return StreamRule(self.stream, self.predicate, convert=convert, unary=self.unary)


class PlatformConfig(BaseModel):
    """One platform's settings, validated at the edge (`load`, `from_dict` name the bad key).

    ``vocabulary`` and ``mapping`` are paths to the TOML files of `docs/ontology.md`, or
    the same content inline. ``export_limit`` bounds the exports (a label to a receiver)
    running at once, ``export_limit_per_platform`` those one other platform asked for,
    ``history_limit_per_platform`` the samples of history kept for one other platform;
    ``import_label`` names the local label of an imported stream, with ``{sender}`` and
    ``{semantic}``. ``sharing`` says what is shared with whom (`SharingSettings`).
    ``facts`` are the rules keeping `FederationPlatform.facts` current (`FactSettings`).
    ``audit``, when set, is the Interface Agent's JSON-lines audit file, rotated at
    ``audit_max_bytes`` with ``audit_backups`` older files kept (`AuditLog`).
    """

    model_config = _SETTINGS

    name: str = Field(pattern=_NAME, description="This platform's name (uav-a, operator).")
    federation: str = Field(pattern=_NAME, description="The federation's name.")
    transport: TransportSettings = Field(default_factory=ZenohSettings)
    key: Path = Field(description="This platform's private key file (agents.keys gen).")
    trust: Path = Field(description="The federation's trust file.")
    vocabulary: Path | dict[str, Any] = Field(description="The federation's vocabulary.")
    mapping: Path | dict[str, Any] = Field(description="This platform's label mapping.")
    export_limit: int = Field(default=64, ge=0)
    # one member must not take every slot (or all the memory history keeps) from the others
    export_limit_per_platform: int = Field(default=32, ge=0)
    history_limit_per_platform: int = Field(default=200_000, ge=0)
    # streams one sender holds here by consent (another member, or itself, asked), started too
    consented_import_limit: int = Field(default=256, ge=0)
    sharing: SharingSettings = Field(default_factory=SharingSettings.model_construct)
    # an export whose receiver has not reported for this long ends ("lease-expired")
    # at least 4 of the receivers' report intervals (0.5 s): a shorter one ends live exports
    export_lease: float | None = Field(default=10.0, ge=2.0, le=86400)
    rate_limit: RateLimitSettings = Field(default_factory=RateLimitSettings.model_construct)
    security: SecuritySettings = Field(default_factory=SecuritySettings.model_construct)
    kx_limit: KxLimitSettings = Field(default_factory=KxLimitSettings.model_construct)
    df_event_limit: DfEventLimitSettings = Field(
        default_factory=DfEventLimitSettings.model_construct
    )
    import_label: str = DEFAULT_IMPORT_LABEL
    audit: Path | None = None
    # a flood must not fill the disk: the audit file's bound, and the rotated files kept
    audit_max_bytes: int = Field(default=AuditLog.DEFAULT_MAX_BYTES, ge=4096)
    audit_backups: int = Field(default=AuditLog.DEFAULT_BACKUPS, ge=0, le=1000)
    console: ConsoleSettings = Field(default_factory=ConsoleSettings.model_construct)
    foxglove: FoxgloveSettings = Field(default_factory=FoxgloveSettings.model_construct)
    facts: list[FactSettings] = Field(default_factory=_no_items)

    # -- the application on this node (docs/application.md): run by `dyknow node` --------
    application: Path | None = Field(default=None, description="The node's KPL file.")
    inputs: list[InputSettings] = Field(default_factory=_no_items)
    outputs: list[OutputSettings] = Field(default_factory=_no_items)

    @field_validator("transport", mode="before")
    @classmethod
    def _default_kind(cls, value: Any) -> Any:
        if isinstance(value, Mapping) and "kind" not in value:
            return {"kind": "zenoh", **value}
        return value

    @field_validator("import_label")
    @classmethod
    def _import_scheme(cls, value: str) -> str:
        try:
            fields = {f for _, f, _, _ in string.Formatter().parse(value) if f is not None}
        except ValueError as exc:
            raise ValueError(f"{value!r} is not a label scheme: {exc}") from None
        unknown = fields - _IMPORT_FIELDS
        if unknown:
            raise ValueError(
                f"{value!r}: unknown placeholder {{{sorted(unknown)[0]}}} "
                "(use {sender} and {semantic})"
            )
        if fields != _IMPORT_FIELDS:
            # without both, two senders (or two labels) would land in one stream
            raise ValueError(f"{value!r} must contain both {{sender}} and {{semantic}}")
        return value

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str = "<config>") -> "PlatformConfig":
        """Validate ``data`` (shaped like the file); PlatformConfigError names the bad key."""
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise _config_error(exc, source) from None

    @classmethod
    def load(cls, path: str | Path) -> "PlatformConfig":
        """Read a TOML config file; relative paths in it are relative to the file."""
        path = Path(path)
        return cls.from_dict(_read_toml(path), source=str(path)).relative_to(path.parent)

    def relative_to(self, base: str | Path) -> "PlatformConfig":
        """A copy whose relative paths are resolved against ``base``."""
        base = Path(base)
        update: dict[str, Any] = {}
        for name in ("key", "trust", "vocabulary", "mapping", "audit"):
            value = getattr(self, name)
            if isinstance(value, Path) and not value.is_absolute():
                update[name] = base / value
        if isinstance(self.transport, ZenohSettings | MqttSettings):  # its TLS (and password) files
            update["transport"] = self.transport.relative_to(base)
        for section in ("console", "foxglove"):
            settings = getattr(self, section)
            token_file = settings.token_file
            if token_file is not None and not token_file.is_absolute():
                update[section] = settings.model_copy(update={"token_file": base / token_file})
        if self.application is not None and not self.application.is_absolute():
            update["application"] = base / self.application
        if self.inputs:
            update["inputs"] = [i.relative_to(base) for i in self.inputs]
        return self.model_copy(update=update)

    @property
    def import_prefix(self) -> str:
        """What every imported stream's local label starts with (``import/`` by default)."""
        return self.import_label.split("{", 1)[0]

    def import_label_of(self, sender: str, semantic: str) -> str:
        """The local label a stream of ``sender``'s ``semantic`` label is imported into."""
        return self.import_label.format(sender=sender, semantic=semantic)

    def make_transport(self) -> Transport:
        """A transport (not yet opened) as ``[transport]`` describes it."""
        if isinstance(self.transport, ZenohSettings):
            return ZenohTransport(self.transport)
        from agents.transports import MqttTransport  # only a platform on MQTT imports it

        return MqttTransport(self.transport)


def _read_toml(path: Path, *, regular: bool = False) -> dict[str, Any]:
    """A TOML file's tables; PlatformConfigError naming the file and why it cannot be read.

    ``regular``: anything else than a regular file (a FIFO, a device) is refused, opened
    without waiting for a writer.
    """
    try:
        with open(path, "rb", opener=_open_nonblocking if regular else None) as f:
            if regular and not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise PlatformConfigError(str(path), None, "is not a regular file")
            return tomllib.load(f)
    except OSError as exc:
        raise PlatformConfigError(str(path), None, f"cannot be read: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise PlatformConfigError(str(path), None, f"not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:  # TOML is UTF-8
        raise PlatformConfigError(
            str(path), None, f"not UTF-8 text: {exc.reason} at byte {exc.start}"
        ) from None
    except RecursionError:  # tomllib recurses into nested arrays and tables
        raise PlatformConfigError(str(path), None, "not valid TOML: nested too deep") from None


def _open_nonblocking(path: str, flags: int) -> int:
    """``os.open`` for ``open(opener=)``, not waiting for a writer (of a FIFO)."""
    return os.open(path, flags | getattr(os, "O_NONBLOCK", 0))


def load_sharing(
    path: str | Path,
    *,
    name: str | None = None,
    federation: str | None = None,
    running: SharingSettings | None = None,
) -> SharingSettings:
    """The ``[sharing]`` table of a TOML config file, once the whole file validates as a
    config (as at start): a truncated or wrong file is refused, not read as the defaults.

    ``name`` / ``federation``: the running platform's; a file of another is refused, and so
    is anything else than a regular file (a FIFO would block the reader). ``running``: the
    policy in force; a file with no ``[sharing]`` table is refused when that is not the
    defaults (a file cut just before the table still validates: it would open every label).
    PlatformConfigError names the file and the key (``sharing.…``, ``name``…).
    """
    path = Path(path)
    data = _read_toml(path, regular=True)
    if "sharing" not in data and running is not None and running != SharingSettings():
        # a file cut short just before its [sharing] still validates: read as the defaults
        # (members), a cut would open every label; returning to them is said explicitly
        raise PlatformConfigError(
            str(path),
            "sharing",
            "missing: a reload never falls back to the defaults; an empty [sharing] table "
            "asks for them",
        )
    if not isinstance(data.get("sharing", {}), dict):
        raise PlatformConfigError(str(path), "sharing", "must be a table")
    config = PlatformConfig.from_dict(data, source=str(path))
    for key, ours in (("name", name), ("federation", federation)):
        if ours is not None and getattr(config, key) != ours:
            raise PlatformConfigError(
                str(path),
                key,
                f"{getattr(config, key)!r} is not the running platform's {ours!r} "
                "(the file of another platform?)",
            )
    return config.sharing


def sharing_changes(old: SharingSettings, new: SharingSettings) -> list[str]:
    """What differs from ``old`` in ``new``, one phrase each (empty: nothing)."""
    changes = []
    for key in ("gateway", "default"):
        before, after = getattr(old, key), getattr(new, key)
        if before != after:
            changes.append(f"sharing.{key} {before!r} -> {after!r}")
    if old.accept_for != new.accept_for:
        changes.append(f"sharing.accept_for {old.accept_for} -> {new.accept_for}")

    def named(rule: SharingRule) -> str:
        return repr(rule.name) if rule.name else f"({', '.join(rule.labels)})"

    changes += [f"rule {named(r)} removed" for r in old.rules if r not in new.rules]
    changes += [f"rule {named(r)} added" for r in new.rules if r not in old.rules]
    if not changes and new.rules != old.rules:
        changes.append("rules reordered")  # the first rule that matches decides
    return changes


def _key_path(loc: tuple[int | str, ...]) -> str:
    """A pydantic location as a key path: ``transport.listen[0]`` (union tags left out)."""
    parts = list(loc)
    if len(parts) >= 2 and parts[0] == "transport" and parts[1] in ("zenoh", "mqtt"):
        del parts[1]
    if len(parts) >= 3 and parts[0] in ("inputs", "outputs") and parts[2] in _KINDS:
        del parts[2]  # the kind's tag
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def _config_error(exc: ValidationError, source: str) -> PlatformConfigError:
    errors = exc.errors(include_url=False)
    first = errors[0]
    key = _key_path(first["loc"])
    message = str(first["msg"]).removeprefix("Value error, ")
    if first["type"] in ("union_tag_invalid", "union_tag_not_found") and key != "transport":
        # an [[inputs]] / [[outputs]] table of an unknown kind, or none
        expected = first.get("ctx", {}).get("expected_tags", "")
        found = first["type"] == "union_tag_invalid"
        key, message = f"{key}.kind", ("expected " + expected if found else "missing")
    elif first["type"] == "union_tag_invalid":
        key, message = f"{key}.kind", "expected 'zenoh' or 'mqtt'"
    elif first["type"] == "missing":
        message = "missing"
    elif first["type"] == "extra_forbidden":
        message = "unknown key"
    elif first["type"] == "string_pattern_mismatch" and key.startswith("sharing"):
        message = f"{first['input']!r}: use letters, digits, '-', '_', '.', '/', * ? [ ] !"
    elif first["type"] == "string_pattern_mismatch":
        message = f"{first['input']!r}: use letters, digits, '-', '_', '.'"
    if len(errors) > 1:
        more = ", ".join(_key_path(e["loc"]) or "<top>" for e in errors[1:])
        message += f" (also wrong: {more})"
    return PlatformConfigError(source, key or None, message)


class _Files:
    """What a config's files hold: the key pair, trust, vocabulary and mapping."""

    # a plain class, not a dataclass: generating a dataclass's methods costs ~0.4 ms of a
    # node's start, each; nothing compares or prints these
    __slots__ = ("keys", "mapping", "trust", "vocabulary")

    def __init__(
        self, keys: KeyPair, trust: TrustStore, vocabulary: Vocabulary, mapping: LabelMapping
    ) -> None:
        self.keys = keys
        self.trust = trust
        self.vocabulary = vocabulary
        self.mapping = mapping


def _read_files(config: PlatformConfig, source: str) -> _Files:
    """Keys, trust, vocabulary and mapping; PlatformConfigError naming the key and why."""
    try:
        keys = KeyPair.load(config.key)
    except (OSError, ValueError, SecurityError) as exc:
        raise PlatformConfigError(source, "key", str(exc)) from None
    if keys.platform != config.name:
        raise PlatformConfigError(
            source, "key", f"{config.key} is the key of {keys.platform!r}, not of {config.name!r}"
        )
    try:
        trust = TrustStore.load(config.trust)
    except (OSError, ValueError, SecurityError) as exc:
        raise PlatformConfigError(source, "trust", str(exc)) from None
    if trust.federation != config.federation:
        raise PlatformConfigError(
            source,
            "trust",
            f"{config.trust} is the trust file of federation {trust.federation!r}, "
            f"not of {config.federation!r}",
        )
    try:
        if isinstance(config.vocabulary, Path):
            vocabulary = Vocabulary.load(config.vocabulary)
        else:
            vocabulary = Vocabulary.from_dict(config.vocabulary, source=f"{source}: vocabulary")
    except OntologyError as exc:
        raise PlatformConfigError(source, "vocabulary", str(exc)) from None
    try:
        if isinstance(config.mapping, Path):
            mapping = LabelMapping.load(config.mapping, vocabulary)
        else:
            mapping = LabelMapping.from_dict(
                config.mapping, vocabulary, source=f"{source}: mapping"
            )
    except OntologyError as exc:
        raise PlatformConfigError(source, "mapping", str(exc)) from None
    unknown = [label for label in config.console.streams if label not in vocabulary]
    if unknown:
        # asked of every member, refused by every one: a wrong config, said at start
        raise PlatformConfigError(
            source,
            "console.streams",
            f"{unknown[0]!r} is not a label of the vocabulary {vocabulary.name or ''}".rstrip(),
        )
    return _Files(keys, trust, vocabulary, mapping)


def _strangers(config: PlatformConfig, trust: TrustStore) -> list[str]:
    """The ``[sharing]`` platform patterns no platform of the trust file matches (a typo)."""
    names = sorted(trust)
    settings = config.sharing
    keyed = [(f"sharing.accept_for[{i}]", p) for i, p in enumerate(settings.accept_for)]
    for r, rule in enumerate(settings.rules):
        keyed += [(f"sharing.rules[{r}].query[{i}]", p) for i, p in enumerate(rule.query)]
        keyed += [(f"sharing.rules[{r}].stream[{i}]", p) for i, p in enumerate(rule.stream)]
    return [
        f"{key}: {pattern!r} names no platform of the trust file {config.trust} "
        f"({', '.join(names)}): it lets no one in"
        for key, pattern in keyed
        if not any(fnmatch.fnmatchcase(name, pattern) for name in names)
    ]


# -- the platform ----------------------------------------------------------------------------

_WHY = {
    "unagreed": "streams this platform did not agree to receive",
    "wrong-sender": "published under another platform's name",
    "wrong-label": "the batch names another label than its key",
}


class _Imports(ImportProxy):
    """The import proxy, telling the platform when an imported stream (re)appears."""

    def __init__(self, *args: Any, on_open: Callable[[Import], None], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._on_open = on_open

    def _open_source(self, rec: Import) -> Source | None:
        source = super()._open_source(rec)
        if source is not None:
            self._on_open(rec)
        return source


def _waiting(rec: Import) -> bool:
    """Whether an agreed import still waits for its first sample (none landed here)."""
    return not rec.injected and rec.source is None


def _unstarted(rec: Import | None) -> bool:
    """Whether an agreed import has seen no batch yet (not even a started export's empty one)."""
    return rec is not None and rec.batches == 0


# why an import dropped samples of authentic batches, for `_import_bad_samples`'s records
_BAD_SAMPLES = {
    "malformed": "not [value, valid time, …]",
    "sender-gone": "its sender left, or its token went, while they were on their way",
}


class FederationPlatform:
    """One platform's assembly, as an async context manager: everything a member needs.

    Built from ``config`` (files are read here: a bad one raises PlatformConfigError).
    ``instance`` and ``transport``, when given, are used instead of new ones and left
    open on exit (their owner closes them). ``join=False`` keeps the platform out of the
    federation until `join` (set up local streams and agents first). ``rules`` keep
    `facts` current from the instance's streams, for label search by formula, after the
    config's ``[[facts]]``. A ``[sharing]`` pattern no trusted platform matches is warned
    when it joins (not by one opened only to ask).
    ``on_import_ended(sender, labels)`` is told when a sender whose streams we import is
    gone (its imported streams are then ended). ``anchor`` is asked when another platform
    wants a stream of an object not known here yet (see `FederationAgent`).
    """

    max_waiting_imports = 256
    """Streams from one sender agreed by consent (another platform asked for them here)
    that may wait for their first batch at once, whoever asked: what other members'
    accept-streams can grow. This platform's own requests and `expect` are not counted."""

    max_waiting_imports_per_requester = 64
    """Of those, how many one requesting platform may have asked for: one member cannot
    use up what the others may ask a sender to stream here."""

    consent_lease = 60.0
    """Seconds a stream agreed by consent may wait for its first batch before it is
    withdrawn (a started export sends at least an empty batch every idle second)."""

    max_consented_imports: int
    """Streams from one sender agreed by consent that this platform holds at once, started
    or not, ended or not (the config's ``consented_import_limit``): a started one no longer
    waits, so the bounds above do not count it, and an ended one keeps its label and
    samples here. Past it an accept-stream is refused (``consent-limit``); the same stream
    asked again is not counted twice. This platform's own requests and `expect` are not
    counted, and what is withdrawn frees its place."""

    def __init__(
        self,
        config: PlatformConfig,
        *,
        instance: DyKnowInstance | None = None,
        transport: Transport | None = None,
        join: bool = True,
        rules: Iterable[Rule] = (),
        gateway_visibility: Visibility | str | None = None,
        on_import_ended: OnImportEnded | None = None,
        source: str | None = None,
        anchor: Anchor | None = None,
    ) -> None:
        self.config = config
        self.name = config.name
        self.max_consented_imports = config.consented_import_limit
        source = source or f"platform {config.name}"
        files = _read_files(config, source)
        # said when it joins the federation (the platform's owner: a node, a console), not
        # by every one-shot command that opens it from the config to ask
        self._sharing_problems = [f"{source}: {p}" for p in _strangers(config, files.trust)]
        self._join_on_open = join
        self.vocabulary = files.vocabulary
        self.mapping = files.mapping
        self._own_instance = instance is None
        self.instance = instance if instance is not None else DyKnowInstance(config.name)
        self._own_transport = transport is None
        self.transport = transport if transport is not None else config.make_transport()
        self.interface = InterfaceAgent(
            files.keys,
            files.trust,
            audit_path=config.audit,
            audit_max_bytes=config.audit_max_bytes,
            audit_backups=config.audit_backups,
            rate_limit=config.rate_limit.to_rate_limit(),
            policy=config.security.to_policy(),
            publish_audit=config.security.audit != "off",
            seal_audit=config.security.audit == "sealed",
            watchable=config.security.watch,
            kx_limit=config.kx_limit.to_kx_limit(),
        )
        self.agents = AgentPlatform(
            config.name,
            self.transport,
            federation=config.federation,
            channel=self.interface,
            df_event_limit=config.df_event_limit.to_df_event_limit(),
        )
        # set by the program: `reload_sharing` leaves it as it is
        self._gateway_fixed = gateway_visibility is not None
        if gateway_visibility is None:
            # private unless the config opens it: local labels never leave the platform
            gateway_visibility = config.sharing.gateway
        self.gateway = GatewayAgent(
            self.instance, visibility=gateway_visibility, reserved=(config.import_prefix,)
        )
        self.facts = FactBase()
        self._rules = [*(f.to_rule() for f in config.facts), *rules]
        self.labels = PlatformLabels(self.mapping, self.instance, self.facts)
        self.exporter = ExportProxy(
            config.name,
            config.federation,
            self.transport,
            self.instance,
            InterfaceSessions(self.interface),
            lease=config.export_lease,
        )
        self.importer = _Imports(
            config.name,
            config.federation,
            self.transport,
            self.instance,
            InterfaceSessions(self.interface),
            self._import_translate,
            on_sender_gone=self._sender_gone,
            on_open=self._import_opened,
            on_export_ended=self._export_ended,
            on_refused=self._import_refused,
            on_bad_samples=self._import_bad_samples,
            # counters of what nobody agreed: a few labels for reading, then one bucket
            max_strays=64,
            presence=self._members_presence,
        )
        # the proxies' subscriptions the transport ends are the platform's losses
        self.exporter.on_lost = self.importer.on_lost = self.agents.ended
        sharing = config.sharing.sharing()
        self.federation_agent = FederationAgent(
            self.instance,
            self.labels,
            exporter=self.exporter,
            search=self.labels,
            max_exports=config.export_limit,
            max_exports_per_platform=config.export_limit_per_platform,
            max_history_per_platform=config.history_limit_per_platform,
            sharing=sharing,
            imports=self,
            # the agent's current policy: a reload (`reload_sharing`) swaps it
            consent=lambda requester, provider, labels: self.federation_agent.sharing.accepts_for(
                requester
            ),
            join=join,
            anchor=anchor,
        )
        self._on_import_ended = on_import_ended
        self._waiters: dict[tuple[str, str], list[asyncio.Future[str]]] = {}
        # sender -> semantic -> (the platform that asked, the end of its consent lease):
        # agreed by `accept`, no batch yet
        self._leased: dict[str, dict[str, tuple[str, asyncio.TimerHandle]]] = {}
        # sender -> the streams agreed by consent (pruned of those no longer agreed or
        # ended when counted): what `max_consented_imports` bounds; each with the platform
        # that asked (a narrowed `sharing.accept_for` withdraws those it no longer accepts)
        self._consented: dict[str, dict[str, str]] = {}
        self._stack: contextlib.AsyncExitStack | None = None
        self.revoked_exports = 0  # exports ended as their platform was revoked, since start
        self.revoked_imports = 0  # imports ended so

    def __repr__(self) -> str:
        return f"<FederationPlatform {self.name} ({self.config.federation})>"

    def _members_presence(self) -> Subscription[Presence]:
        """Senders coming and going as the global directory authenticated them."""
        gdf = self.agents.global_df
        if gdf is None:
            raise RuntimeError("the platform keeps no global directory")
        return gdf.watch_presence()

    @classmethod
    def from_file(cls, path: str | Path, **options: Any) -> "FederationPlatform":
        """A platform from a TOML config file (see `PlatformConfig.load`)."""
        return cls(PlatformConfig.load(path), source=str(path), **options)

    # -- lifecycle ------------------------------------------------------------------------

    async def __aenter__(self) -> Self:
        if self._stack is not None:
            raise RuntimeError(f"{self!r} was opened already; a platform cannot reopen")
        stack = self._stack = contextlib.AsyncExitStack()
        try:
            if self._own_instance:
                await stack.enter_async_context(self.instance)
            if self._own_transport:
                await stack.enter_async_context(self.transport)
            await stack.enter_async_context(self.agents)
            await self.agents.add(self.gateway)
            await stack.enter_async_context(self.exporter)
            # Receiving before joining: a stream agreed the moment we are listed must land.
            await stack.enter_async_context(self.importer)
            if self._rules:
                await stack.enter_async_context(FactFeed(self.instance, self.facts, self._rules))
            # Stopped before the proxies close: its teardown stops exports through them.
            stack.push_async_callback(self.agents.remove, self.federation_agent)
            await self.agents.add(self.federation_agent)
            # after the Interface Agent's (hooked as it started): its sessions go first
            stack.callback(self.interface.trust.on_remove(self._trust_removed))
        except BaseException:
            await stack.aclose()
            raise
        log.info("platform %s: running in federation %s", self.name, self.config.federation)
        if self._join_on_open:
            self._say_sharing_problems()
        return self

    def _say_sharing_problems(self) -> None:
        """Warn, once, of the ``[sharing]`` patterns no trusted platform matches."""
        for problem in self._sharing_problems:
            log.warning("%s", problem)
        self._sharing_problems = []

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Leave and tear everything down, in the reverse order of building it."""
        stack = self._stack
        if stack is None:
            return
        for leases in self._leased.values():
            for _, handle in leases.values():
                handle.cancel()  # not while the import proxy closes
        self._leased.clear()
        try:
            await stack.aclose()
        finally:
            for waiters in self._waiters.values():
                for fut in waiters:
                    fut.cancel()
            self._waiters.clear()

    # -- the sharing policy ---------------------------------------------------------------

    async def reload_sharing(
        self, settings: SharingSettings, *, source: str | None = None
    ) -> tuple[list[str], list[tuple[str, str, str, str]]]:
        """Apply a new ``[sharing]`` table now: (what changed, the exports ended).

        The Federation Agent's policy is swapped in one assignment: every check after it
        (query, create-stream, consent) applies the new one. The exports it no longer
        allows end (their receivers are told; see `FederationAgent.end_unshared`); what it
        newly allows is served to the next request. A changed ``gateway`` re-registers
        the Gateway Agent's service with it (unless the program set its visibility:
        ``gateway_visibility=``); made private, the gateway's subscriptions of other
        platforms end and the streams they created through it are removed (but for one
        a staying process reads: kept, handed to this platform). The streams agreed here
        by consent (flowing or leased) whose requester ``accept_for`` no longer lets
        direct streams here are withdrawn (they end here). Audited: ``policy``
        ``reloaded``, and ``policy`` ``ended`` for each export ended (``sharing-rule``),
        each gateway subscription ended and each created stream removed
        (``sharing-gateway``; ``kept`` for one kept) and each stream withdrawn
        (``accept-for``).
        """
        source = source or f"platform {self.name}"
        old = self.federation_agent.sharing.settings
        changes = sharing_changes(old, settings)
        why = f"the sharing policy was reloaded from {source}"
        gone = GatewayEnded([], [], [])  # the gateway's subscriptions and created streams
        if self._gateway_fixed:
            if settings.gateway != old.gateway:
                kept = self.gateway.visibility.value
                changes.append(f"the Gateway Agent stays {kept!r} (set by the program)")
        elif (actual := self.gateway.visibility) is not Visibility(settings.gateway):
            # what the gateway serves with, not the old file: they differ after a failed
            # reload, and then the same file again must not be "no change"
            if settings.gateway == old.gateway:
                changes.append(
                    f"the Gateway Agent re-registered {settings.gateway!r} "
                    f"(it served {actual.value!r})"
                )
            # first: a re-registration that fails leaves the whole policy in force; the
            # subscriber is told no more than an export's receiver (UNSHARED_WHY)
            gone = await self.gateway.set_visibility(settings.gateway, UNSHARED_WHY)
        told = _gateway_told(gone)
        changes.extend(what for _, _, _, _, what, _ in told)
        self.federation_agent.sharing = settings.sharing()
        self.config = self.config.model_copy(update={"sharing": settings})
        audit = self.interface.audit
        audit.record(
            verdict="reloaded",
            stage="policy",
            reason=f"[sharing] reloaded from {source}: " + ("; ".join(changes) or "no change"),
        )
        for problem in _strangers(self.config, self.interface.trust):
            log.warning("%s: %s", source, problem)
        for verdict, label, agent, role, what, more in told:
            audit.record(
                verdict=verdict,
                stage="policy",
                code="sharing-gateway",
                stream=label,
                to=platform_of(agent),
                **{role: agent},
                reason=f"{what}{more}: {why}: sharing.gateway is {settings.gateway!r}",
            )
        ended = await self.federation_agent.end_unshared(why)
        self._audit_exports_ended(ended, stage="policy", code="sharing-rule", why=why)
        for sender, semantic, requester, reason in self._withdraw_unaccepted():
            audit.record(
                verdict="ended",
                stage="policy",
                code="accept-for",
                stream=semantic,
                requester=requester,
                **{"from": sender},
                reason=(
                    f"import of {semantic!r} from {sender}, asked for by {requester}, "
                    f"withdrawn: {why}: {reason}"
                ),
            )
        return changes, ended

    def _audit_exports_ended(
        self,
        ended: list[tuple[str, str, str, str]],
        *,
        stage: str,
        code: str,
        why: str | None = None,
    ) -> None:
        """Audit each export ``ended`` (id, label, receiver, reason) by a reload or a
        revocation: ``verdict: ended``, the reason after ``why`` when given."""
        for export_id, semantic, receiver, reason in ended:
            self.interface.audit.record(
                verdict="ended",
                stage=stage,
                code=code,
                stream=semantic,
                to=receiver,
                export=export_id,
                reason=f"export {export_id} of {semantic!r} to {receiver} ended: "
                + (reason if why is None else f"{why}: {reason}"),
            )

    def _withdraw_unaccepted(
        self, refusal: Callable[[str], str | None] | None = None
    ) -> list[tuple[str, str, str, str]]:
        """Withdraw the streams agreed by consent (flowing or leased) whose requester
        ``refusal`` (by default ``sharing.accept_for``) refuses now: (sender, label,
        requester, refusal) of each."""
        refuse = refusal or self.federation_agent.sharing.accepts_for
        gone = []
        for sender, held in list(self._consented.items()):
            for semantic, requester in list(held.items()):
                reason = refuse(requester)
                if reason is None:
                    continue
                del held[semantic]
                gone.append((sender, semantic, requester, reason))
                log.warning(
                    "platform %s: %r from %s (asked for by %s) withdrawn: %s",
                    self.name,
                    semantic,
                    sender,
                    requester,
                    reason,
                )
                self.withdraw(sender, semantic)
            if not held:
                del self._consented[sender]
        return gone

    # -- revocation -----------------------------------------------------------------------

    def reload_trust(self, new: TrustStore, *, source: str | None = None) -> list[str]:
        """Trust from now on the platforms of ``new`` (the trust file re-read): what changed.

        A platform no longer in it is revoked as `TrustStore.remove` does (its sessions
        forgotten, its exports and imports ended, what it created at the gateway removed);
        one added is trusted; one with another key is revoked, then trusted with the new
        key. ValueError, and nothing changes, when ``new`` is another federation's or holds
        another key for this platform. This platform's own entry is never revoked.
        Audited: ``trust`` ``reloaded`` (the revocations audit what they end).
        """
        trust = self.interface.trust
        source = source or str(self.config.trust)
        if new.federation != trust.federation:
            raise ValueError(
                f"{source} is the trust file of federation {new.federation!r}, "
                f"not {trust.federation!r}"
            )
        me = self.name
        if me in new and new.public_key(me) != self.interface.keys.public_key:
            raise ValueError(f"{source} holds another key for {me!r} than this platform's key pair")
        old = set(trust) - {me}
        now = set(new) - {me}
        revoked = sorted(old - now)
        added = sorted(now - old)
        rekeyed = sorted(p for p in old & now if new.public_key(p) != trust.public_key(p))
        changes = []
        if revoked:
            changes.append("revoked " + ", ".join(map(repr, revoked)))
        if rekeyed:
            changes.append("revoked and trusted with a new key " + ", ".join(map(repr, rekeyed)))
        if added:
            changes.append("trusted " + ", ".join(map(repr, added)))
        if me in trust and me not in new:
            changes.append(f"{me!r} (this platform) is not in it: kept")
        self.interface.audit.record(
            verdict="reloaded",
            stage="trust",
            reason=f"trust file reloaded from {source}: " + ("; ".join(changes) or "no change"),
        )
        # after the record: what each revocation ends is audited after it, as a
        # [sharing] reload's ends are
        for platform in revoked:
            trust.remove(platform)
        for platform in rekeyed:
            trust.remove(platform)
            trust.add(platform, new.public_key(platform))
        for platform in added:
            trust.add(platform, new.public_key(platform))
        return changes

    def _trust_removed(self, platform: str) -> None:
        """The trust store's callback: end what ``platform`` holds here, in the platform's
        event loop (`_revoked`; the Interface Agent forgot its sessions already)."""
        agent = self.federation_agent
        loop = agent._loop
        if loop is None or platform == self.name:
            return  # stopped meanwhile; or this platform's own name

        def start() -> None:
            with contextlib.suppress(AgentError):  # stopping: its teardown ends them all
                agent.spawn(self._revoked(platform), f"revoked[{platform}]")

        call_in_loop(loop, start)

    async def _revoked(self, platform: str) -> None:
        """``platform`` was removed from the trust file: its exports and imports here end,
        then it leaves the global directory and the members.

        The exports to it (or that it asked for) stop, it told nothing; the streams agreed
        from it end here (as withdrawn: their later batches would be refused anyway).
        Counted (``revoked_exports``, ``revoked_imports``), audited (``stage: trust``,
        ``code: untrusted``, ``verdict: ended``) and logged.
        """
        why = f"platform {platform!r} was removed from the trust file (revoked)"
        audit = self.interface.audit
        ended = await self.federation_agent.end_revoked(platform)
        self.revoked_exports += len(ended)
        self._audit_exports_ended(ended, stage="trust", code="untrusted")  # each ended by `why`
        self._consented.pop(platform, None)
        for rec in self.importer.imports(platform):
            semantic = rec.semantic_label
            ended_before = rec.ended  # counted and audited then: forgotten, not ended again
            self._unlease(platform, semantic)
            self.importer.forget(platform, semantic)
            if ended_before:
                continue
            self.revoked_imports += 1
            audit.record(
                verdict="ended",
                stage="trust",
                code="untrusted",
                stream=semantic,
                **{"from": platform},
                reason=f"import of {semantic!r} from {platform} ended: {why}",
            )
            log.warning(
                "platform %s: import of %r from %s ended: %s", self.name, semantic, platform, why
            )
        # what it directed here from other platforms (agreed by consent) goes too
        for sender, semantic, requester, _ in self._withdraw_unaccepted(
            lambda requester: why if requester == platform else None
        ):
            self.revoked_imports += 1
            audit.record(
                verdict="ended",
                stage="trust",
                code="untrusted",
                stream=semantic,
                requester=requester,
                **{"from": sender},
                reason=f"{semantic!r} from {sender}, asked for by {requester}, withdrawn: {why}",
            )
        # last, once what it held here ended as revoked: no member any more, out of the
        # global directory (its watchers, the members here among them, told it is gone)
        if platform not in self.interface.trust and self.agents.global_df is not None:
            self.agents.global_df.revoked(platform)

    # -- membership -----------------------------------------------------------------------

    async def join(self) -> None:
        """Register the federation service: the platform becomes a member."""
        self._say_sharing_problems()
        await self.federation_agent.join()

    async def leave(self) -> None:
        """Deregister the federation service; streams already agreed keep flowing."""
        await self.federation_agent.leave()

    @property
    def members(self) -> list[str]:
        """The members now, by the signed directory events (this one included if joined).

        One that just joined is a member before its signed snapshot answered here (a
        global request asks it already): the platforms listed (`GlobalDirectory.listed`,
        ``agents.global_df.listed``) are what a stream receiver must be
        (`docs/federation.md`).
        """
        return self.federation_agent.members

    def membership(self, maxlen: int = 1024) -> Subscription[MembershipEvent]:
        """Membership changes (joined, left, gone) from now on, as an async iterator."""
        return self.federation_agent.membership(maxlen)

    # -- imports --------------------------------------------------------------------------

    def import_label(self, sender: str, semantic: str) -> str:
        """The local label ``sender``'s stream of ``semantic`` lands in here.

        UnknownSemanticLabel when ``semantic`` is not in the federation's vocabulary.
        """
        self.vocabulary.entry(semantic)
        rec = self.importer.get(sender, semantic)
        if rec is not None and rec.local_label is not None:
            return rec.local_label
        return self.config.import_label_of(sender, semantic)

    async def imported(self, sender: str, semantic: str, *, timeout: float = 10.0) -> str:
        """Wait until ``sender``'s ``semantic`` stream has arrived here; its local label."""
        label = self.import_label(sender, semantic)
        rec = self.importer.get(sender, semantic)
        if rec is not None and rec.source is not None and not rec.ended:
            return label
        fut: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        key = (sender, semantic)
        self._waiters.setdefault(key, []).append(fut)
        try:
            async with asyncio.timeout(timeout):
                return await fut
        except TimeoutError:
            raise TimeoutError(
                f"no sample of {semantic!r} from {sender} arrived within {timeout} s"
            ) from None
        finally:
            waiters = self._waiters.get(key)
            if waiters is not None and fut in waiters:
                waiters.remove(fut)
                if not waiters:
                    del self._waiters[key]

    def expect(self, sender: str, semantic: str) -> str:
        """Agree to receive ``sender``'s stream of ``semantic``: the local label it lands in.

        The import proxy accepts only agreed streams; the Federation Agent agrees to what
        it asks for (and what ``sharing.accept_for`` lets others ask for here). Call this
        when an agent asks a provider for a stream other than through the Federation Agent.
        It is agreed for good: a create-stream of the Federation Agent's that waits for the
        same stream and fails no longer withdraws it, nor does a consent lease end it.
        UnknownSemanticLabel when ``semantic`` is not in the federation's vocabulary.
        """
        label = self._agree(sender, semantic)
        self._unlease(sender, semantic)
        self._consented.get(sender, {}).pop(semantic, None)  # ours now
        self.federation_agent.keep_import(sender, semantic)
        return label

    def accept(
        self, sender: str, semantic: str, requester: str, /, *, pending: bool = False
    ) -> str:
        """Agree to receive a stream ``requester`` asked ``sender`` to send here.

        The Federation Agent calls it when it consents to an ``accept-stream``. Unless it
        was agreed already, the agreement lasts ``consent_lease`` seconds if no batch of
        the stream arrives meanwhile (a stream that started stays). ``pending``: agreed
        already, but only by a request of ours not answered yet; it goes under the lease
        too (that request accepted, it is agreed for good). ValueError when
        ``max_waiting_imports`` such agreements with ``sender`` wait already, or
        ``max_waiting_imports_per_requester`` of them that ``requester`` asked for;
        Denied (``consent-limit``) when ``sender`` holds ``max_consented_imports`` here
        that have not ended (waiting or flowing).
        """
        rec = self.importer.get(sender, semantic)
        leases = self._leased.get(sender, {})
        if rec is not None and rec.local_label is not None and (not pending or semantic in leases):
            return rec.local_label
        waiting = [r for s, (r, _) in leases.items() if _unstarted(self.importer.get(sender, s))]
        limit, own = self.max_waiting_imports, self.max_waiting_imports_per_requester
        if len(waiting) >= limit:
            raise ValueError(
                f"{len(waiting)} streams from {sender} that other platforms asked for here "
                f"have sent nothing yet (at most {limit}): {semantic!r} not agreed"
            )
        mine = waiting.count(requester)
        if mine >= own:
            raise ValueError(
                f"{mine} streams from {sender} that {requester} asked for here have sent "
                f"nothing yet (at most {own} per requester): {semantic!r} not agreed"
            )
        held = self._consented.setdefault(sender, {})
        get = self.importer.get
        # only those not ended count: an ended one is withdrawn (its samples stay readable),
        # else a batch of it would start it again here uncounted; a new consent agrees it
        for s in [s for s in held if (r := get(sender, s)) is None or r.ended]:
            del held[s]
            if s != semantic:
                self.importer.forget(sender, s)
        if semantic not in held and len(held) >= self.max_consented_imports:
            # started streams wait no more: without this a provider that may ask for
            # itself streams here as many as it likes, one batch each
            raise Denied(
                "consent-limit",
                f"{sender} holds {len(held)} streams here agreed by consent (at most "
                f"{self.max_consented_imports}): {semantic!r} not agreed",
            )
        label = self._agree(sender, semantic)
        held[semantic] = requester
        handle = asyncio.get_running_loop().call_later(
            self.consent_lease, self._lease_ended, sender, semantic
        )
        self._leased.setdefault(sender, {})[semantic] = (requester, handle)
        return label

    def _agree(self, sender: str, semantic: str) -> str:
        """Record in the import proxy that ``sender``'s ``semantic`` lands here."""
        label = self.import_label(sender, semantic)
        rec = self.importer.get(sender, semantic)
        if rec is None or rec.local_label is None:
            self.importer.expect(sender, semantic, label)
        return label

    def _unlease(self, sender: str, semantic: str) -> None:
        """The stream is agreed for good, or not at all: its consent lease ends."""
        leases = self._leased.get(sender)
        if leases is None:
            return
        lease = leases.pop(semantic, None)
        if lease is not None:
            lease[1].cancel()
        if not leases:
            del self._leased[sender]

    def _lease_ended(self, sender: str, semantic: str) -> None:
        # a consent nobody acted on: the provider never started the export (or refused)
        self._unlease(sender, semantic)
        if _unstarted(self.importer.get(sender, semantic)):
            log.info("platform %s: %r from %s never came: withdrawn", self.name, semantic, sender)
            self.importer.forget(sender, semantic)

    def agreed(self, sender: str, semantic: str) -> bool:
        """Whether this platform agreed to receive ``sender``'s stream of ``semantic``."""
        return self.importer.get(sender, semantic) is not None

    def withdraw(self, sender: str, semantic: str, *, gave_up: bool = False) -> None:
        """Undo `expect` for a stream whose create-stream did not succeed: it ends here.

        The Federation Agent withdraws what its create-stream expected when the provider
        refuses, fails or does not answer (``gave_up``: and the export is cancelled). A
        stream whose samples arrived meanwhile (they may overtake the answer) ends too:
        the provider stopped what it started, or the cancel stops it, and neither sends
        an end marker, so it would never end here. Its subscribers' iterators end, its
        samples stay readable under its label, later batches of it are dropped as
        unagreed and a later request asks again.
        """
        if self.importer.get(sender, semantic) is None:
            return
        self._unlease(sender, semantic)
        self.importer.forget(sender, semantic)

    def _import_translate(self, sender: str, semantic: str) -> None:
        # what this platform did not agree (`expect`) is dropped and counted: "unagreed"
        return None

    def _import_refused(self, sender: str, reason: str, batches: int, samples: int) -> None:
        # one record per sender and reason per report interval: a flood is summed up
        self.interface.audit.record(
            verdict="dropped",
            stage="import",
            code=reason,
            count=batches,
            **{"from": sender},
            reason=(
                f"{reason}: {batches} batch(es), {samples} sample(s) from {sender!r} dropped "
                f"by the import proxy ({_WHY.get(reason, 'not accepted')})"
            ),
        )

    def _import_bad_samples(self, sender: str, label: str, reason: str, samples: int) -> None:
        # one record per stream and reason per report interval: a flood is summed up
        self.interface.audit.record(
            verdict="dropped",
            stage="import-samples",
            code=reason,
            count=samples,
            stream=label,
            **{"from": sender},
            reason=(
                f"{reason}: {samples} sample(s) of {sender!r}'s stream {label!r} dropped from "
                "authentic batches by the import proxy ("
                + _BAD_SAMPLES.get(reason, "refused here")
                + ")"
            ),
        )

    def _import_opened(self, rec: Import) -> None:
        for fut in self._waiters.pop((rec.sender, rec.semantic_label), []):
            if not fut.done() and rec.local_label is not None:
                fut.set_result(rec.local_label)

    def _export_ended(self, sender: str, semantic: str) -> None:
        # the sender stopped it (its lease for us expired): a durable stream is asked again
        self.federation_agent.export_ended(sender, semantic)

    async def _sender_gone(self, sender: str, labels: list[str]) -> None:
        # Membership subscribers hear "gone" from the Federation Agent (the global
        # directory follows the same liveliness token); here the imports are what ended.
        # An agreed stream whose first sample never came did not end: it never flowed.
        recs = [(s, self.importer.get(sender, s)) for s in labels]
        waited = [s for s, rec in recs if rec is not None and _waiting(rec)]
        flowed = [s for s in labels if s not in waited]
        if flowed:
            log.warning(
                "platform %s: %s is gone; its streams imported here ended: %s",
                self.name,
                sender,
                ", ".join(flowed),
            )
        if waited:
            log.warning(
                "platform %s: %s is gone; its streams agreed here that were waiting for "
                "their first sample will not come: %s",
                self.name,
                sender,
                ", ".join(waited),
            )
        hook = self._on_import_ended
        if hook is not None:
            result = hook(sender, labels)
            if inspect.isawaitable(result):
                await result

    # -- fusion ---------------------------------------------------------------------------

    async def fuse(
        self,
        semantic: str,
        sender: str,
        output: str,
        *,
        window: float = 0.5,
        combine: Callable[[Any, Any], Any] | None = None,
        timeout: float = 10.0,
    ) -> Fusion:
        """Fuse our own ``semantic`` stream with ``sender``'s import, preferring ours.

        Waits (at most ``timeout`` s) for the imported stream's first sample, which is
        fused with the ones after it; ``output`` is a local label (see `add_fusion` for
        ``window`` and ``combine``).
        """
        local = self.labels.to_local(semantic)
        imported = await self.imported(sender, semantic, timeout=timeout)
        # what arrived while we waited (the first sample at least) is fused too: left out,
        # the first fused sample of a 0.5 s stream would come a period later than need be
        return add_fusion(
            self.instance, local, imported, output, window=window, combine=combine, replay=True
        )
