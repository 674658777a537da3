"""The ``dyknow`` commands (typer; rich for tables): every subcommand, one style of flags.

``federation.cli.main`` is the entry point: it runs a plain ``dyknow node -c FILE``
without this module (``_cli_node``), everything else through `app`.

The same flag means the same thing in every command: ``--config/-c`` is this platform's
TOML config, ``--platform/-p`` the platform asked (or whose key it is), ``--json``
machine-readable output instead of text, ``--wait`` seconds to wait for the federation
to be seen, ``--timeout`` seconds to wait for the asked platform's answer. Semantic
labels are arguments. Times in text output are ISO 8601 with the local offset, durations
seconds, and a time given to a command may be written the same way (``_cli_time``).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import os
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from agents import TransportError
from agents import run as run_loop

from ._cli_common import complain, error_text
from ._cli_node import CONFIG_FLAGS, CONFIG_HELP, log_to_stderr, run_node
from ._cli_node import say as _say
from ._cli_reasoning import kpl_app, monitor
from ._cli_time import asked, parse_time, when, when_ns
from ._platform import PlatformConfig, PlatformConfigError

if TYPE_CHECKING:
    from rich.table import Table

    from ontology import Vocabulary


def _demo_app() -> typer.Typer:
    from .demo import demo_app

    return demo_app


app = typer.Typer(
    name="dyknow",
    help="DyKnow Federation tools.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.command("monitor")(monitor)
app.add_typer(kpl_app, name="kpl")
keys_app = typer.Typer(
    help="A platform's key pair and the federation's trust file.", no_args_is_help=True
)
app.add_typer(keys_app, name="keys")
app.add_typer(_demo_app(), name="demo")


def _table(title: str, *columns: str, whole: tuple[str, ...] = ()) -> Table:
    """A rich table with these columns (rich is imported by the commands that print one).

    The columns named in ``whole`` keep each cell on one line; the others give up width.
    """
    from rich.table import Table

    table = Table(title=title)
    for column in columns:
        # folded, not cut with an ellipsis: a time or label cut short on an 80-column
        # terminal (or a pipe) says nothing
        table.add_column(column, overflow="fold", no_wrap=column in whole)
    return table


def _print(table: Table) -> None:
    """Print a rich table to stdout."""
    from rich.console import Console

    Console(highlight=False, soft_wrap=True).print(table)


ConfigOpt = Annotated[Path, typer.Option(*CONFIG_FLAGS, help=CONFIG_HELP)]
PlatformOpt = Annotated[str, typer.Option("--platform", "-p", help="the platform to ask")]
LabelsArg = Annotated[list[str], typer.Argument(metavar="LABELS", help="semantic labels")]
JsonOpt = Annotated[
    bool, typer.Option("--json", help="print JSON instead of text (a stream: one object a line)")
]
WaitOpt = Annotated[
    float, typer.Option("--wait", help="seconds to wait for the federation to be seen")
]
TimeoutOpt = Annotated[
    float, typer.Option("--timeout", help="seconds to wait for the asked platform's answer")
]
TrustFileOpt = Annotated[Path, typer.Option("--trust-file", help="the federation's trust file")]
FederationOpt = Annotated[
    str | None, typer.Option("--federation", help="the federation of a new trust file")
]


def _fail(message: str, code: int = 2) -> typer.Exit:
    """Print ``message`` on stderr; the Exit to raise."""
    complain(message)
    return typer.Exit(code)


def _load(config: Path) -> PlatformConfig:
    """Load a config or exit 2 naming the file and the key."""
    try:
        return PlatformConfig.load(config)
    except PlatformConfigError as exc:
        raise _fail(str(exc)) from None


def _in_vocabulary(command: str, cfg: PlatformConfig, labels: Sequence[str]) -> None:
    """Exit 2 naming a label the config's vocabulary lacks: a typo is said before asking.

    A provider would refuse it all the same, but maybe by its sharing rules first,
    which do not say that the label is no label at all.
    """
    vocabulary = _vocabulary_of(cfg)
    if vocabulary is None:
        return
    unknown = [label for label in labels if label not in vocabulary]
    if unknown:
        name = f" {vocabulary.name}" if vocabulary.name else ""
        raise _fail(f"dyknow {command}: {unknown[0]!r} is not a label of the vocabulary{name}")


def _vocabulary_of(cfg: PlatformConfig) -> Vocabulary | None:
    """The platform's vocabulary, or None when it cannot be read (its start says why)."""
    from ontology import OntologyError, Vocabulary

    try:
        if isinstance(cfg.vocabulary, Path):
            return Vocabulary.load(cfg.vocabulary)
        return Vocabulary.from_dict(cfg.vocabulary)
    except OntologyError:
        return None


def _formula_checked(cfg: PlatformConfig, formula: str) -> None:
    """Exit 2 on a formula that does not parse or uses a concept the vocabulary lacks.

    As the console's search refuses it (a 400): said before asking, not as each
    provider's refusal.
    """
    from ontology import OntologyError, parse

    try:
        expr = parse(formula)
    except OntologyError as exc:
        raise _fail(f"dyknow labels: --formula: {exc}") from None
    vocabulary = _vocabulary_of(cfg)
    if vocabulary is None:
        return
    try:
        vocabulary.check(expr)
    except OntologyError as exc:
        raise _fail(f"dyknow labels: --formula: {exc}") from None


# -- keys ---------------------------------------------------------------------------------------


@contextlib.contextmanager
def _keys_failure(command: str) -> Iterator[None]:
    """A `KeysError` in the block: said as ``dyknow keys COMMAND`` failing, exit 1."""
    from agents.keys import KeysError

    try:
        yield
    except KeysError as exc:
        raise _fail(f"dyknow keys {command}: {exc}", 1) from None


@keys_app.command("gen")
def keys_gen(
    platform: Annotated[str, typer.Option("--platform", "-p", help="the platform's name")],
    directory: Annotated[Path, typer.Option("--dir", "-d", help="where the key files go")],
    trust_file: Annotated[
        Path | None, typer.Option("--trust-file", help="also trust the new public key here")
    ] = None,
    federation: FederationOpt = None,
    force: Annotated[
        bool, typer.Option("--force", help="overwrite existing key files (lock-out risk)")
    ] = False,
) -> None:
    """Generate a platform's key pair (private key 0600), optionally trusting it."""
    from agents.keys import check_trust_file, gen_keys, trust_keys

    with _keys_failure("gen"):
        if trust_file is not None:  # a trust file it cannot use: refused before any key is made
            check_trust_file(trust_file, federation)
        pair, key_path, pub_path = gen_keys(platform, directory, force=force)
        _say(f"created {key_path} (private, mode 0600: keep it on {platform} only)")
        _say(f"created {pub_path} (public: add it to the federation's trust file)")
        _say(f"fingerprint {platform} {pair.fingerprint}")
        if trust_file is not None:
            for line in trust_keys(trust_file, [pub_path], federation=federation):
                _say(line)


@keys_app.command("trust")
def keys_trust(
    trust_file: TrustFileOpt,
    pubs: Annotated[list[Path], typer.Argument(metavar="PUBS", help="public key files")],
    federation: FederationOpt = None,
    replace: Annotated[
        bool, typer.Option("--replace", help="rotate: accept a new key for a known platform")
    ] = False,
) -> None:
    """Add public key files (.pub) to the federation's trust file."""
    from agents.keys import trust_keys

    with _keys_failure("trust"):
        for line in trust_keys(trust_file, pubs, federation=federation, replace=replace):
            _say(line)


@keys_app.command("untrust")
def keys_untrust(
    trust_file: TrustFileOpt,
    platforms: Annotated[
        list[str], typer.Argument(metavar="PLATFORMS", help="platform names to stop trusting")
    ],
) -> None:
    """Remove platforms from the trust file (revoke them; a running node: send it SIGHUP)."""
    from agents.keys import untrust

    with _keys_failure("untrust"):
        for line in untrust(trust_file, platforms):
            _say(line)


@keys_app.command("show")
def keys_show(trust_file: TrustFileOpt) -> None:
    """List the platforms a trust file accepts, with their key fingerprints."""
    from agents.keys import show

    with _keys_failure("show"):
        for line in show(trust_file):
            _say(line)


# -- node, router -------------------------------------------------------------------------------


@app.command("node")
def node(config: ConfigOpt) -> None:
    """Run one platform from its TOML config until SIGINT/SIGTERM."""
    code = run_node(config)  # what `dyknow node -c FILE` runs without typer (_cli_node)
    if code:
        raise typer.Exit(code)


@app.command("console")
def console(
    config: ConfigOpt,
    host: Annotated[str, typer.Option("--host", help="the address to serve on")] = "127.0.0.1",
    port: Annotated[int, typer.Option("--port", help="the HTTP port (0: any free one)")] = 8080,
    allow_host: Annotated[
        list[str] | None,
        typer.Option(
            "--allow-host",
            help="a host name the console may be reached by, besides localhost and IP "
            "addresses (repeatable; adds to console.allow_hosts and "
            "$DYKNOW_CONSOLE_ALLOW_HOSTS)",
        ),
    ] = None,
    token_file: Annotated[
        Path | None,
        typer.Option(
            "--token-file",
            help="a file holding the console's token (else $DYKNOW_CONSOLE_TOKEN, else "
            "console.token_file, else a random one, printed with the URL)",
        ),
    ] = None,
) -> None:
    """Run a platform with the operator web console (docs/console.md) until SIGINT/SIGTERM."""
    from ._cli_net import run_console
    from ._local import PlatformAliveError
    from .console import allowed_names, configured_token

    cfg = _load(config)
    try:
        token = configured_token(token_file, cfg.console.token_file)
        hosts = allowed_names([*cfg.console.allow_hosts, *(allow_host or [])], os.environ)
    except ValueError as exc:
        raise _fail(f"dyknow console: {config}: {exc}") from None
    try:
        with log_to_stderr():
            run_loop(
                run_console(cfg, str(config), host, port, _say, token=token, allow_hosts=hosts)
            )
    except PlatformConfigError as exc:
        raise _fail(str(exc)) from None
    except PlatformAliveError as exc:
        raise _fail(f"dyknow console: {config}: {exc}") from None
    except (TransportError, OSError) as exc:
        raise _fail(f"dyknow console: {config}: {_serving(exc, host, port)}", 1) from None


def _serving(exc: Exception, host: str, port: int) -> str:
    """What stopped a console or bridge, its port in use said in plain words."""
    if isinstance(exc, OSError) and exc.errno == errno.EADDRINUSE:
        return (
            f"cannot serve on {host}:{port}: the address is in use (by another console, "
            "or another program): stop that one, or choose another --port (0: any free one)"
        )
    return str(exc)


@app.command("foxglove")
def foxglove(
    config: ConfigOpt,
    host: Annotated[
        str, typer.Option("--host", help="the address to serve on (clients only watch)")
    ] = "127.0.0.1",
    port: Annotated[
        int, typer.Option("--port", help="the WebSocket port (0: any free one)")
    ] = 8765,
    sample_period: Annotated[
        float | None,
        typer.Option("--sample-period", min=0.0, help="seconds between samples asked"),
    ] = None,
    allow_host: Annotated[
        list[str] | None,
        typer.Option(
            "--allow-host",
            help="a host name Foxglove may connect by, besides localhost and IP addresses "
            "(repeatable; adds to foxglove.allow_hosts, else console.allow_hosts, and "
            "$DYKNOW_CONSOLE_ALLOW_HOSTS)",
        ),
    ] = None,
    token_file: Annotated[
        Path | None,
        typer.Option(
            "--token-file",
            help="a file holding the token (else $DYKNOW_CONSOLE_TOKEN, else "
            "foxglove.token_file, else console.token_file, else a random one, printed "
            "with the URL)",
        ),
    ] = None,
) -> None:
    """Run a platform serving its federation's streams to Foxglove (docs/foxglove.md)."""
    from ._cli_net import run_foxglove
    from ._local import PlatformAliveError
    from .console import allowed_names, configured_token

    cfg = _load(config)
    fox = cfg.foxglove
    try:
        token = configured_token(token_file, fox.token_file or cfg.console.token_file)
        configured = cfg.console.allow_hosts if fox.allow_hosts is None else fox.allow_hosts
        hosts = allowed_names([*configured, *(allow_host or [])], os.environ)
    except ValueError as exc:
        raise _fail(f"dyknow foxglove: {config}: {exc}") from None
    try:
        with log_to_stderr():
            run_loop(
                run_foxglove(
                    cfg,
                    str(config),
                    host,
                    port,
                    _say,
                    sample_period=sample_period,
                    token=token,
                    allow_hosts=hosts,
                )
            )
    except PlatformConfigError as exc:
        raise _fail(str(exc)) from None
    except ValueError as exc:  # [foxglove] names what the federation does not have
        raise _fail(f"dyknow foxglove: {config}: {exc}") from None
    except PlatformAliveError as exc:
        raise _fail(f"dyknow foxglove: {config}: {exc}") from None
    except (TransportError, OSError) as exc:
        raise _fail(f"dyknow foxglove: {config}: {_serving(exc, host, port)}", 1) from None
    except RuntimeError as exc:  # the SDK's server could not start
        raise _fail(f"dyknow foxglove: {config}: {exc}", 1) from None


@app.command("router")
def router(
    zenoh_config: Annotated[
        Path | None,
        typer.Option("--zenoh-config", help="a zenoh JSON5 config (TLS, access control, …)"),
    ] = None,
    listen: Annotated[
        list[str] | None,
        typer.Option("--listen", help="an endpoint, e.g. tcp/0.0.0.0:7447 (repeatable)"),
    ] = None,
) -> None:
    """A zenoh router (zenoh's router mode) until SIGINT/SIGTERM."""
    from pydantic import ValidationError

    from ._cli_net import read_json5, run_router

    if zenoh_config is None and not listen:
        listen = ["tcp/0.0.0.0:7447"]
    try:
        json5 = read_json5(None if zenoh_config is None else str(zenoh_config))
    except OSError as exc:
        raise _fail(f"{zenoh_config}: cannot be read: {exc.strerror}") from None
    try:
        run_loop(run_router(list(listen or []), json5, _say))
    except ValidationError as exc:
        msgs = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise _fail(f"{zenoh_config or 'dyknow router'}: {msgs}") from None
    except Exception as exc:  # zenoh.ZError (e.g. the port is taken): no traceback
        raise _fail(f"dyknow router: {exc}", 1) from None


# -- one-shot queries ---------------------------------------------------------------------------


def _alive_error() -> tuple[type[Exception], ...]:
    from ._local import ForeignNodeError, PlatformAliveError

    return PlatformAliveError, ForeignNodeError


def _relayed_error() -> type[Exception]:
    from ._cli_net import RelayedError

    return RelayedError


def _run_query(coro: Any) -> Any:
    """Run a query coroutine; config and request errors exit 2 / 1 with a message."""
    try:
        return asyncio.run(coro)
    except PlatformConfigError as exc:
        raise _fail(str(exc)) from None
    except _alive_error() as exc:
        raise _fail(f"dyknow: {exc}") from None
    except _relayed_error() as exc:  # the node's text is in words already
        raise _fail(f"dyknow: {exc}", 1) from None
    except Exception as exc:  # the user gets the reason, not a traceback
        raise _fail(f"dyknow: {error_text(exc)}", 1) from None


@app.command("platforms")
def platforms(config: ConfigOpt, as_json: JsonOpt = False, wait: WaitOpt = 3.0) -> None:
    """List the platforms listed in the federation and their public services.

    Listed: alive, and their signed directory snapshot answered (the platforms a stream may
    go to); one that joined a moment ago may be a member already and not listed yet.
    """
    from ._cli_net import dumps, list_platforms

    _load(config)
    found = _run_query(list_platforms(str(config), wait))
    if as_json:
        _say(dumps(found))
        return
    # a service name is what a user copies into the next command: one line, not folded
    table = _table(
        "platforms listed", "platform", "service", "type", "provider", whole=("service",)
    )
    for name, services in found.items():
        if not services:
            table.add_row(name, "-", "-", "-")
        for s in services:
            table.add_row(name, s["name"], s["type"], s["provider"])
    _print(table)


@app.command("labels")
def labels(
    config: ConfigOpt,
    platform: PlatformOpt,
    formula: Annotated[
        str | None, typer.Option("--formula", help="FIPA-SL formula to search labels by")
    ] = None,
    as_json: JsonOpt = False,
    wait: WaitOpt = 3.0,
    timeout: TimeoutOpt = 10.0,
) -> None:
    """The semantic labels a platform provides (or those matching an SL formula)."""
    from ._cli_net import ask_platform, dumps

    cfg = _load(config)
    if formula is not None:
        _formula_checked(cfg, formula)
    content: dict[str, Any] = (
        {"action": "list-labels"}
        if formula is None
        else {"action": "search-labels", "formula": formula}
    )
    answer = _run_query(ask_platform(str(config), platform, content, wait, timeout))
    if as_json:
        _say(dumps(answer))
        return
    table = _table(f"labels of {platform}", "semantic label")
    for label in answer.get("labels", []):
        table.add_row(label)
    _print(table)


@app.command("ask")
def ask(
    label_names: LabelsArg,
    config: ConfigOpt,
    platform: PlatformOpt,
    at: Annotated[
        str | None,
        typer.Option("--at", help="value at T (ISO 8601 with offset, POSIX s, now, -10s)"),
    ] = None,
    since: Annotated[
        str | None,
        typer.Option("--from", help="trajectory from T (ISO 8601 with offset, POSIX s, now, -2m)"),
    ] = None,
    until: Annotated[
        str | None, typer.Option("--to", help="trajectory until T (as --from)")
    ] = None,
    as_json: JsonOpt = False,
    wait: WaitOpt = 3.0,
    timeout: TimeoutOpt = 10.0,
) -> None:
    """Latest value (default), value --at T, or samples --from T [--to T] of labels."""
    from ._cli_net import ask_platform, dumps

    _in_vocabulary("ask", _load(config), label_names)
    if at is not None and (since is not None or until is not None):
        raise _fail("dyknow ask: --at cannot be combined with --from/--to")
    content: dict[str, Any] = {"labels": label_names}
    try:
        if at is not None:
            t, rel = parse_time(at)
            content.update({"action": "get-value-at", "t": t, "relative": rel})
        elif since is not None or until is not None:
            content["action"] = "get-trajectory"
            rels = []
            for key, text in (("from", since), ("to", until)):
                if text is not None:
                    value, rel = parse_time(text)
                    content[key] = value
                    rels.append(rel)
            if len(set(rels)) > 1:
                raise ValueError("--from and --to must both be relative or both absolute")
            content["relative"] = rels[0]
        else:
            content["action"] = "get-latest"
    except ValueError as exc:
        raise _fail(f"dyknow ask: {exc}") from None
    answer = _run_query(ask_platform(str(config), platform, content, wait, timeout))
    if as_json:
        _say(dumps(answer))
        return
    title = content["action"]
    rel = content.get("relative", False)
    if "t" in content:
        title += f" {asked(content['t'], rel)}"
    elif title == "get-trajectory":
        low = asked(content["from"], rel) if "from" in content else "the start"
        high = asked(content["to"], rel) if "to" in content else "now"
        title += f" {low} .. {high}"
    table = _table(f"{title} from {platform}", "label", "query time", "value", "valid", "available")
    for label, result in answer.items():
        samples = result.get("samples", []) if isinstance(result, dict) else []
        qt = result.get("query_time") if isinstance(result, dict) else None
        shown = when(qt) if isinstance(qt, int | float) else "-"
        if not samples:
            table.add_row(label, shown, "-", "-", "-")
        for value, valid, available in samples:
            table.add_row(label, shown, repr(value), when(valid), when(available))
    _print(table)


@app.command("stream")
def stream(
    label_names: LabelsArg,
    config: ConfigOpt,
    platform: PlatformOpt,
    sample_period: Annotated[
        float | None, typer.Option("--sample-period", help="seconds between samples")
    ] = None,
    count: Annotated[
        int | None, typer.Option("--count", "-n", min=1, help="stop after N samples in all")
    ] = None,
    as_json: JsonOpt = False,
    wait: WaitOpt = 3.0,
    timeout: TimeoutOpt = 10.0,
) -> None:
    """Create a stream from a platform to this one and print its samples (Ctrl-C stops)."""
    from ._cli_net import follow_stream

    _in_vocabulary("stream", _load(config), label_names)

    def emit(label: str, value: Any, valid: int, available: int) -> None:
        if as_json:
            row = {"label": label, "value": value, "valid": valid, "available": available}
            _say(json.dumps(row, default=str))
        else:
            _say(f"{label}  valid={when_ns(valid)}  available={when_ns(available)}  {value!r}")

    _run_query(
        follow_stream(
            str(config),
            platform,
            label_names,
            sample_period=sample_period,
            count=count,
            wait=wait,
            timeout=timeout,
            emit=emit,
        )
    )


# -- the owner's watch ----------------------------------------------------------------------------


def _watch_line(event: dict[str, Any]) -> str:
    """One watched event as a line of text (as JSON when its fields are not as expected)."""
    try:
        return _watch_text(event)
    except (TypeError, ValueError, KeyError, AttributeError, OverflowError, OSError):
        # what opened need not be a well-formed message: a member may send anything
        return f"{event.get('kind')} {json.dumps(event, default=repr)}"


def _watch_text(event: dict[str, Any]) -> str:
    kind = event["kind"]
    stamp = when(event.get("ts") or time.time())
    if kind == "acl":
        m = event["message"]
        if not isinstance(m, dict):
            return f"{stamp} acl    from {event['from']}: {m!r}"
        receivers = ",".join(m.get("receivers", []))
        content = json.dumps(m.get("content"), default=str)
        return (
            f"{stamp} acl    {m.get('performative')} {m.get('sender')} -> {receivers} "
            f"[{m.get('ontology')}] {content}"
        )
    if kind == "stream":
        b = event["batch"]
        samples = b.get("b", []) if isinstance(b, dict) else []
        label = b.get("s") if isinstance(b, dict) else None
        shown = ", ".join(repr(s[0]) for s in samples[:4]) + (" …" if len(samples) > 4 else "")
        return f"{stamp} stream from {event['from']} {label}: {len(samples)} sample(s) {shown}"
    if kind == "stream-report":
        return f"{stamp} report from {event['from']}: {json.dumps(event['report'], default=str)}"
    if kind == "audit":
        r = event["record"]
        stage = f" ({r['stage']})" if r.get("stage") else ""
        # a record about no peer (the owner's own watch) has no 'from': say nothing of it
        who = [f"from {r['from']}"] if r.get("from") else []
        who += [str(r[k]) for k in ("performative", "sender") if r.get(k)]
        head = " ".join([f"{r.get('verdict')}{stage}", *who])
        reason = r.get("reason")
        # a record with no reason ends at its head: no colon left dangling
        return f"{stamp} audit  {head}: {reason}" if reason else f"{stamp} audit  {head}"
    if kind == "watching":
        line = f"watching {event['platform']}: messages, batches and audit addressed to it"
        if event.get("signed", True):
            return line
        # the bound then rests on this side's clock: a batch recorded up to the allowance
        # before the watch began could pass as current
        return (
            f"{line}\nwarning: the platform's answer was not signed (an older release, or "
            "anyone answering in its place): batches are bounded by this side's clock less "
            f"the {event.get('allowance_s', 0):g} s clock allowance"
        )
    return f"{stamp} {kind} {json.dumps(event, default=str)}"


@app.command("watch")
def watch(
    config: ConfigOpt,
    as_json: JsonOpt = False,
    duration: Annotated[
        float | None, typer.Option("--duration", min=0.0, help="stop after S seconds")
    ] = None,
    timeout: TimeoutOpt = 10.0,
) -> None:
    """As the platform's owner (its key): watch, decrypted, what reaches the running platform."""
    from ._cli_net import watch_platform

    _load(config)

    def emit(event: dict[str, Any]) -> None:
        _say(json.dumps(event, default=repr) if as_json else _watch_line(event))

    # its transport's warnings and its own loss (ERROR) said as a node says them
    with log_to_stderr():
        _run_query(watch_platform(str(config), emit, duration=duration, timeout=timeout))


# -- record and replay --------------------------------------------------------------------------


@app.command("record")
def record(
    label_names: LabelsArg,
    config: ConfigOpt,
    platform: PlatformOpt,
    out: Annotated[
        Path, typer.Option("--out", "-o", help="the recording to write (MCAP, e.g. flight.mcap)")
    ],
    duration: Annotated[
        float | None, typer.Option("--duration", min=0.0, help="stop after S seconds")
    ] = None,
    count: Annotated[
        int | None, typer.Option("--count", "-n", min=1, help="stop after N samples in all")
    ] = None,
    sample_period: Annotated[
        float | None, typer.Option("--sample-period", help="seconds between samples")
    ] = None,
    wait: WaitOpt = 3.0,
    timeout: TimeoutOpt = 10.0,
) -> None:
    """Record streams of a platform to a file (Ctrl-C or SIGTERM stops, the file complete).

    Creates the streams like 'dyknow stream' does and writes every sample that arrives
    (value, valid and available time, semantic label) to OUT, an MCAP file (one channel
    per label, JSON) that Foxglove opens, in chunks flushed every second, with a progress
    line on stderr. 'dyknow replay OUT' plays it back.
    """
    from ._record_cli import record_federation

    _in_vocabulary("record", _load(config), label_names)
    if not out.parent.is_dir():
        raise _fail(f"dyknow record: --out {out}: directory {out.parent} does not exist")
    rec = _run_query(
        record_federation(
            str(config),
            platform,
            label_names,
            out,
            duration=duration,
            count=count,
            sample_period=sample_period,
            wait=wait,
            timeout=timeout,
            progress=complain,
        )
    )
    counts = ", ".join(f"{k}={n}" for k, n in sorted(rec.counts.items()))
    _say(f"dyknow record: {rec.recorded} samples ({counts or '-'}) written to {out}")


@app.command("replay")
def replay_recording(
    file: Annotated[
        Path,
        typer.Argument(
            metavar="FILE", help="the recording: MCAP, a rosbag2 bag (directory) or an old .dkr"
        ),
    ],
    kpl_spec: Annotated[
        Path | None, typer.Option("--kpl", help="a KPL application to set up and feed")
    ] = None,
    print_labels: Annotated[
        list[str] | None,
        typer.Option("--print", help="a stream to print as it is produced (repeatable)"),
    ] = None,
    speed: Annotated[
        float | None, typer.Option("--speed", help="1 = real time, 2 = twice as fast")
    ] = None,
    tail: Annotated[
        float, typer.Option("--tail", min=0.0, help="seconds the clock runs on at the end")
    ] = 0.0,
    as_json: JsonOpt = False,
    show_info: Annotated[
        bool, typer.Option("--info", help="only show the header and per-label counts")
    ] = False,
    node_config: Annotated[
        Path | None,
        typer.Option(
            "--config",
            "-c",
            help="a node's config: its mapping turns the recorded semantic labels into the "
            "local ones its KPL names (and --kpl defaults to its application)",
        ),
    ] = None,
) -> None:
    """Replay a recording through a local instance on a manual clock (deterministic).

    FILE is a recording of 'dyknow record', any MCAP file (JSON and ROS 2 channels; each
    topic a label) or a rosbag2 bag.

    The clock is advanced to each sample's available time before it is pushed into a
    source of its label, so the same recording always gives the same outputs; it runs
    as fast as possible unless --speed is given. With --kpl the application is set up
    first: recorded labels it declares as sources (or does not mention) are fed by the
    recording, recorded labels it computes are recomputed, not fed. --print picks the
    streams printed as they are produced (default: with --kpl every stream the recording
    does not feed, without it the recorded samples). A summary ends the output.

    A recording of 'dyknow record' holds semantic labels (temperature); a node's KPL
    names local ones (wx/temperature): --config NODE.toml replays the recorded labels
    under that node's mapping, into its application unless --kpl names another.
    """
    from dyknow_core import RecordError

    from ._record_cli import (
        ReplayUsageError,
        check_speed,
        info,
        info_lines,
        load_mapping,
        print_sample,
        run_replay,
        summary_lines,
    )

    try:
        if show_info:
            data = info(file)
            if as_json:
                _say(json.dumps(data, indent=2, sort_keys=True, default=str))
            else:
                for line in info_lines(data):
                    _say(line)
            return
        mapping = None
        if node_config is not None:
            mapping, application = load_mapping(node_config)
            kpl_spec = kpl_spec or application
        result = asyncio.run(
            run_replay(
                file,
                kpl=kpl_spec,
                mapping=mapping,
                prints=print_labels or None,
                speed=check_speed(speed),
                tail=tail,
                emit=print_sample(as_json, _say),
                warn=complain,
            )
        )
    except (ReplayUsageError, RecordError) as exc:
        raise _fail(str(exc)) from None
    except Exception as exc:  # the user gets the reason, not a traceback
        raise _fail(f"dyknow replay: {type(exc).__name__}: {exc}", 1) from None
    if as_json:
        _say(json.dumps({"summary": result}, sort_keys=True, default=str))
    else:
        for line in summary_lines(result):
            _say(line)
