"""One platform, one process: the local channel of a running node, and the duplicate check.

A platform's name is its identity in the federation (its key, its sessions with the
others, its liveliness token). Two processes under one name break each other's
sessions, so:

* a node (``dyknow node`` / ``dyknow console``) refuses to start when its name is alive
  in the federation already (`refuse_duplicate`), before it subscribes or announces
  anything: the running one is not touched. On one host a node listening on the local
  channel below decides (no outsider can flood it); across hosts, a presence confirmed
  by a signed directory answer;
* a running node listens on a **local channel**, a Unix socket only its own OS user can
  open (a 0700 directory, the socket 0600, and the peer's uid checked), and the one-shot
  commands (``platforms``, ``labels``, ``ask``, ``stream``, ``record``) run with the same
  config go through it: the node asks, under its own sessions, and relays the answers
  (a ``stream`` of the node's own platform follows its own instance: no export).
  Whoever can open the socket could read the platform's private key file as well (same
  user), so the channel gives nothing the key would not. Without a running node the
  commands act as the platform themselves, as before.

The channel belongs to the platform's identity, its key, not only to its names: the
socket's name carries the public key's fingerprint, and the node states its key first
on every connection, so a command with the config of another deployment that uses the
same federation and platform names (other keys) never reaches this node.

The channel's protocol: to a client of its own OS user the node first sends ``{"node":
{"platform": name, "federation": federation, "ed25519": its public key, base64}}`` on a
line (to another user's, once its request line came, only the refusal); the client, once
it sees that key is its config's, sends one JSON object on a line (``op``: ``platforms``,
``request`` or ``stream``, with their arguments); the node answers with JSON lines:
``{"ok": result}``, or ``{"sample": [label, value, valid, available]}`` lines then
``{"end": n}``, or ``{"error": "message"}``. See docs/application.md.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import errno
import fcntl
import hashlib
import json
import logging
import math
import os
import resource
import secrets
import socket
import stat
import struct
import threading
import time
from collections.abc import AsyncGenerator, Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from nacl.exceptions import BadSignatureError
from nacl.signing import VerifyKey

from agents import (
    KeyPair,
    Pending,
    SecurityError,
    TokenBucket,
    TransportError,
    TrustStore,
    quoted,
    runs_signed,
    wire_key,
)
from dyknow_core import Policy

from ._cli_common import (
    NotAnsweredError,
    error_text,
    failure_of,
    platforms_of,
    reaching,
    wait_for_members,
)
from ._cli_time import seconds, when
from ._gateway_service import MIN_REMOTE_PERIOD
from ._platform import PlatformConfig

if TYPE_CHECKING:
    from agents.transports import Reply, Transport

    from ._platform import FederationPlatform

__all__ = [
    "ForeignNodeError",
    "LocalChannel",
    "LocalChannelError",
    "NodeUnreachable",
    "PlatformAliveError",
    "channel_path",
    "refuse_duplicate",
    "via_node",
]

log = logging.getLogger(__name__)

_SUN_PATH = 100  # bytes of a Unix socket's path, with a margin (108 on Linux, 104 on BSDs)
_LINE = 1 << 20  # longest request line accepted (1 MiB)
_REFUSE_WAIT = 5.0  # s a refused client has to send its request before the refusal
_HELLO_WAIT = 10.0  # s a node has to state its key once a command connected
_IDENTITY_WAIT = 2.0  # s the refusal waits for the running node to say where it runs
_REQUEST_WAIT = 30.0  # s a command has to send its request once the node stated its key
ALIVE_WAIT = 1.0
"""Seconds one ask for a platform's token may take (zenoh returns once every peer answered)."""
IDENTITY_RATE = 10.0
"""``identity`` queries a node answers per second (bursts as many); the rest are shed."""


# -- the duplicate check ---------------------------------------------------------------------


class PlatformAliveError(RuntimeError):
    """A platform of this name is alive in the federation already; this one must not start."""


def _identity(config: PlatformConfig, started: float) -> dict[str, Any]:
    """What a running node tells a second one of its name: where it runs, since when."""
    return {
        "platform": config.name,
        "federation": config.federation,
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "since": started,
    }


def identity_key(config: PlatformConfig) -> str:
    """The key a running node answers ``who are you`` queries on."""
    return wire_key(config.federation, "identity", config.name)


def alive_key(config: PlatformConfig) -> str:
    """The liveliness token of a platform of this config's name."""
    return wire_key(config.federation, "alive", config.name)


async def refuse_duplicate(
    transport: Transport, config: PlatformConfig, wait: float = ALIVE_WAIT, *, command: bool = False
) -> None:
    """PlatformAliveError when ``config``'s name is alive already (on an open ``transport``).

    ``command``: the refused one is a one-shot command (the message says where to run it).
    """
    # On this host first: a node listening on our own channel (a 0700 directory of ours)
    # is this platform running, whatever the network says; nobody outside can flood that.
    try:
        path = channel_path(config)
    except NodeUnreachable:  # its key unreadable: the platform's own start says why
        path = None
    here = None if path is None else await _node_here(path)
    if here is not None:
        raise await _alive_error(transport, config, here, command)
    # Every platform's token asked, not only ours: any other's in the answer shows the
    # session is routed to the federation already, so ours missing from it is known at
    # once. Only ours kept: a flood of invented presences cannot crowd it out.
    own = alive_key(config)
    alive = await transport.tokens(
        wire_key(config.federation, "alive", "*"), timeout=wait, keep=own.__eq__
    )
    if own not in alive:
        return
    # A presence is only a hint (anyone on an open network can declare one): the name
    # runs when it answers a fresh directory query with a statement signed by its key.
    try:
        keys, trust = KeyPair.load(config.key), TrustStore.load(config.trust)
    except Exception as exc:  # the platform's own start says what is wrong with them
        log.debug("reading the keys to check a presence: %s", exc)
    else:
        if not await runs_signed(transport, keys, trust, config.name):
            log.warning(
                "a presence of %r answers no signed directory query: not a running "
                "platform on this host (none listens on its local channel), and taken for "
                "forged or gone elsewhere; starting. If it does run on another host while "
                "its directory is flooded with queries, this start is a second process of it",
                config.name,
            )
            return
    raise await _alive_error(transport, config, None, command)


async def _node_here(path: Path) -> int | None:
    """The pid of the node listening on the local channel ``path``; None when none listens.

    0 when one listens but its pid is unknown. A socket nobody listens on is a dead
    node's (connecting is refused at once). ForeignNodeError when the listener is
    another OS user's: never taken for this platform running, never unlinked.
    LocalChannelError when this host cannot look (out of file descriptors or memory):
    never taken for none listening, so never unlinked either.
    """
    # A Unix socket's connect is decided in the kernel at once (no round trip, no accept):
    # made without blocking, no wait of the loop's can be taken for a busy listener on a
    # loaded machine; a full backlog (EAGAIN) is someone listening, busy.
    try:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    except OSError as exc:
        raise _cannot_look(path, exc) from None
    try:
        sock.setblocking(False)
        try:
            sock.connect(str(path))
        except BlockingIOError:
            return 0
        except OSError as exc:
            if exc.errno in _SHORT_OF:
                # not "none listens": the caller would unlink a live node's socket
                raise _cannot_look(path, exc) from None
            return None  # no socket, or a stale one (refused), or not ours to open
        creds = _socket_cred(sock)
    finally:
        sock.close()
    if creds is None:  # no SO_PEERCRED here (not Linux): someone listens
        return 0
    pid, uid = creds
    if uid != os.getuid():
        raise ForeignNodeError(_not_ours_listener(path, uid))
    return pid


_SHORT_OF = {errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM}
"""Errors that say this host is short of descriptors or memory, nothing of the channel."""


class LocalChannelError(OSError):
    """This host lacks what looking at the local channel takes (file descriptors, memory),
    or a usable directory to place it in."""


def _cannot_look(path: Path, exc: OSError) -> LocalChannelError:
    """The error for ``exc`` met looking for a node on ``path``, its cause in words."""
    return _short_of(
        exc,
        f"cannot tell whether a node of this platform runs on this host (its local channel {path})",
    )


def _short_of(exc: OSError, doing: str) -> LocalChannelError:
    """``doing`` (what failed, in words) and the cause of ``exc`` (out of what)."""
    if exc.errno == errno.EMFILE:
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        cause = (
            f"this process is out of file descriptors (at most {soft} open at once: "
            "RLIMIT_NOFILE; raise it, e.g. `ulimit -n 4096`, or find what holds them)"
        )
    elif exc.errno == errno.ENFILE:
        cause = "the system's file table is full (fs.file-max): too many files open on this host"
    elif exc.errno in (errno.ENOBUFS, errno.ENOMEM):
        cause = "the system is out of memory (for sockets and files)"
    else:
        cause = exc.strerror or str(exc)
    return LocalChannelError(f"{doing}: {cause}")


def _since(pid: int) -> float | None:
    """When process ``pid`` of this host started (POSIX s); None where /proc does not say."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        ticks = int(stat.rsplit(")", 1)[1].split()[19])  # starttime: clock ticks after boot
        boot = next(
            int(line.split()[1])
            for line in Path("/proc/stat").read_text().splitlines()
            if line.startswith("btime ")
        )
        return boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


async def _alive_error(
    transport: Transport, config: PlatformConfig, here: int | None, command: bool
) -> PlatformAliveError:
    """The refusal: where the running one is (``here``: its pid, when it runs on this host)."""
    where = "where and since when unknown (it did not say)"
    if here is not None:
        local = {"pid": here or "unknown", "host": socket.gethostname(), "since": _since(here)}
        where = _where(local)
    try:
        # the first answer that fits ends the query: a queryable that never answers
        # (anyone may declare one) would otherwise hold it to its timeout
        async with await transport.ask(identity_key(config), timeout=_IDENTITY_WAIT) as replies:
            async for reply in replies:
                info = _identity_of(reply)
                if info is None or info.get("platform") != config.name:
                    continue
                # unauthenticated: on this host, only the answer of the pid listening here
                if here and (info.get("pid") != here or info.get("host") != socket.gethostname()):
                    continue
                where = _where(info)
                break
    except Exception as exc:  # the error says it is alive either way, only less precisely
        log.debug("asking the running platform where it runs: %s", exc)
    who = f"platform {config.name!r} is alive in federation {config.federation!r} already"
    if command and here is not None:  # it started since the command looked for it
        return PlatformAliveError(
            f"{who}: {where}. Run this command again: it goes through the running node"
        )
    if command:
        return PlatformAliveError(
            f"{who}: {where}. Acting as it from here would break its sessions: run this command on "
            "its host (it goes through the running node there), or with a config of a "
            "platform of its own"
        )
    return PlatformAliveError(
        f"{who}: {where}. A platform runs in one process: stop that one first, or give this one "
        "a name of its own (the one-shot commands go through the running node)"
    )


def _identity_of(reply: Reply) -> dict[str, Any] | None:
    """A running node's answer to an identity query; None for an error or junk reply."""
    if not reply.ok:
        return None
    try:
        info = json.loads(reply.payload)
    except ValueError:
        return None
    return info if isinstance(info, dict) else None


def _where(info: dict[str, Any]) -> str:
    """``pid 123 on host h, since 2026-…+01:00 (300 s ago)`` from a running node's answer."""
    since = info.get("since")
    started = "since an unknown time"
    if isinstance(since, int | float):
        ago = round(max(0.0, time.time() - since))
        started = f"since {when(since)} ({seconds(ago)} ago)"
    return f"pid {info.get('pid')} on host {info.get('host')!r}, {started}"


# -- the local channel -----------------------------------------------------------------------


def channel_path(config: PlatformConfig, keys: KeyPair | None = None) -> Path:
    """Where the node of ``config`` listens: ``…/dyknow/<federation>/<name>-<fingerprint>.sock``.

    Under ``$XDG_RUNTIME_DIR``, or ``<tmp>/dyknow-<uid>/`` without it; the directories are
    made 0700. ``<fingerprint>``: of the platform's public key (of ``keys``, or read from
    ``config.key``; NodeUnreachable when it cannot be), so two deployments that use the same
    names with other keys have channels of their own. A path too long for a socket becomes
    ``<tmp>/dyknow-<uid>/<its hash>.sock``. LocalChannelError when ``<tmp>`` is needed and
    there is no usable temporary directory.
    """
    if keys is None:
        keys = _keys_of(config)
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime:
        base = Path(runtime) / "dyknow"
    else:
        try:
            base = _tmp_top()
        except OSError as exc:
            raise _no_tmp(config, "without $XDG_RUNTIME_DIR it goes there", exc) from None
    path = base / config.federation / f"{config.name}-{keys.fingerprint}.sock"
    size = len(os.fsencode(path))
    if size > _SUN_PATH:
        # a socket's path has ~107 bytes at most: a short one named by the long one's hash
        # (the long one names the key's fingerprint, so the hash stands for it too)
        digest = hashlib.sha256(os.fsencode(path)).hexdigest()[:24]
        try:
            path = _tmp_top() / f"{digest}.sock"
        except OSError as exc:
            why = f"its path {path} is {size} bytes, too long for a socket ({_SUN_PATH} at most)"
            raise _no_tmp(config, why, exc, "or XDG_RUNTIME_DIR to a shorter one") from None
    return path


def _tmp_top() -> Path:
    """``<tmp>/dyknow-<uid>``: asked for only when needed (finding ``<tmp>`` may fail)."""
    # imported here: with $XDG_RUNTIME_DIR set a node never needs it, and tempfile brings
    # shutil and its compressors (bz2, lzma: ~0.6 MB of an idle node's memory)
    import tempfile

    return Path(tempfile.gettempdir()) / f"dyknow-{os.getuid()}"


def _no_tmp(config: PlatformConfig, why: str, exc: OSError, more: str = "") -> LocalChannelError:
    """The local channel of ``config`` needs the temporary directory (``why``), and there is
    no usable one (``exc``, `tempfile.gettempdir`'s): what to set, in words."""
    return LocalChannelError(
        f"cannot place the local channel of platform {config.name!r} under the temporary "
        f"directory ({why}): there is no usable one ({exc}); set TMPDIR to a directory "
        f"this user may write{', ' + more if more else ''}"
    )


def _keys_of(config: PlatformConfig) -> KeyPair:
    """The key pair of ``config``'s platform; NodeUnreachable when its key file is unusable
    (LocalChannelError when this host is short of descriptors or memory to read it).

    Without its key a command cannot tell its node from another deployment's: it acts as the
    platform itself, whose start then says what is wrong with the key.
    """
    try:
        return KeyPair.load(config.key)
    except (OSError, ValueError, SecurityError) as exc:
        # this host short of descriptors or memory is no unusable key: taken for one, a
        # command would act as the platform itself beside its running node
        cause = exc if isinstance(exc, OSError) else exc.__context__  # a KeyFileError's OSError
        if isinstance(cause, OSError) and cause.errno in _SHORT_OF:
            raise _short_of(cause, f"cannot read the platform's key {config.key}") from None
        raise NodeUnreachable(f"the platform's key cannot be read: {exc}") from None


def _hello(config: PlatformConfig, public_key: bytes) -> dict[str, Any]:
    """The line a node states who it is with, first on every connection."""
    return {
        "node": {
            "platform": config.name,
            "federation": config.federation,
            "ed25519": base64.b64encode(public_key).decode("ascii"),
        }
    }


def _own_top(path: Path) -> Path:
    """The first directory of ours above the socket directory ``path``.

    ``$XDG_RUNTIME_DIR/dyknow`` or ``<tmp>/dyknow-<uid>``: the runtime or temporary
    directory above it is the system's, never checked nor changed.
    """
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime:
        top = Path(runtime) / "dyknow"
        if top == path or top in path.parents:
            return top
    top = _tmp_top()
    if top == path or top in path.parents:
        return top
    return path


def _private_dir(path: Path, *, make: bool = True) -> bool:
    """Check every directory from ours at the top down to ``path`` is ours and 0700.

    ``make`` (the node): make those missing (0700) and tighten ours that are looser; else
    (a command) False when one is missing. ForeignNodeError when one is another user's
    (made there before us, as in a shared ``<tmp>``) or not a directory (a link): a
    channel there could be theirs.
    """
    top = _own_top(path)
    chain = [path, *path.parents]
    for d in reversed(chain[: chain.index(top) + 1]):
        if make:
            with contextlib.suppress(FileExistsError):
                d.mkdir(mode=0o700)
        try:
            st = os.lstat(d)
        except FileNotFoundError:
            if make:
                raise
            return False
        if not stat.S_ISDIR(st.st_mode):
            raise ForeignNodeError(
                f"{d} is not a directory (a link?): the local channel is not placed under it; "
                "remove it"
            )
        if st.st_uid != os.getuid():
            raise ForeignNodeError(
                f"{d} belongs to uid {st.st_uid}, not to this user (uid {os.getuid()}): "
                "another user made it first, so a local channel under it could be theirs; "
                "remove it, or set XDG_RUNTIME_DIR to a directory of this user's"
            )
        if make and st.st_mode & 0o077:  # a command checks the listener's uid instead
            os.chmod(d, 0o700)
    return True


def _peer_cred(writer: asyncio.StreamWriter) -> tuple[int, int] | None:
    """(pid, uid) of the process on the other end of a Unix socket; None where unknown."""
    sock = writer.get_extra_info("socket")
    return None if sock is None else _socket_cred(sock)


def _socket_cred(sock: socket.socket) -> tuple[int, int] | None:
    """(pid, uid) of the process on the other end of ``sock``; None where unknown.

    SO_PEERCRED (Linux): of a listener, its credentials when it began to listen.
    """
    option = getattr(socket, "SO_PEERCRED", None)
    if option is None:
        return None
    creds = sock.getsockopt(socket.SOL_SOCKET, option, struct.calcsize("3i"))
    pid, uid, _gid = struct.unpack("3i", creds)
    return int(pid), int(uid)


def _peer_uid(writer: asyncio.StreamWriter) -> int | None:
    creds = _peer_cred(writer)
    return None if creds is None else creds[1]


def _not_ours_listener(path: Path, uid: int | None) -> str:
    """Why the listener on ``path`` is not taken for a node of this user's."""
    if uid is None:
        return (
            f"the listener on {path} cannot be checked to be this user's (no SO_PEERCRED on "
            "this system): nothing was sent to it"
        )
    return (
        f"the listener on {path} runs as uid {uid}, not as this user (uid {os.getuid()}): "
        "not a node of this config, so nothing was sent to it; stop it, or remove the socket"
    )


def _proof_data(config: PlatformConfig, nonce: bytes) -> bytes:
    """What a node signs to show a command it holds its config's key (for ``nonce``)."""
    return b"\0".join(
        (b"dyknow local channel", config.federation.encode(), config.name.encode(), nonce)
    )


class _Shared:
    """An export the channel made for commands: its id, key, sample period, commands following."""

    __slots__ = ("export_id", "following", "key", "sample_period")

    def __init__(self, export_id: str, key: tuple[str, str], sample_period: Any) -> None:
        self.export_id = export_id
        self.key = key
        self.sample_period = sample_period
        self.following = 1


class _Pending:
    """An operation on a stream under way (its create, or its cancel): wait for it.

    ``done`` is set once it ends; ``error`` is what a failed create-stream raised (a
    cancel never sets one: its export ends with its lease there anyway).
    """

    __slots__ = ("done", "error")

    def __init__(self) -> None:
        self.done = asyncio.Event()
        self.error: Exception | None = None


class LocalChannel:
    """A running node's local channel and its ``who are you`` answer (async context manager)."""

    def __init__(self, platform: FederationPlatform) -> None:
        self.platform = platform
        keys = platform.interface.keys
        self.path = channel_path(platform.config, keys)
        self._hello = json.dumps(_hello(platform.config, keys.public_key)).encode() + b"\n"
        self._keys = keys
        self.started = time.time()
        self._server: asyncio.base_events.Server | None = None
        self._bound: tuple[int, int] | None = None  # the socket's (device, inode) once bound
        self._handle: Any = None
        self.served = 0
        self.refused = 0
        self._lock = asyncio.Lock()
        self._exports: dict[tuple[str, str], _Shared] = {}  # by (target, semantic label)
        # the imports this channel created: once cancelled, such an import is never the
        # node's own, even while its end is still on its way (one the node made since is
        # another record, and the node's)
        self._made: dict[tuple[str, str], Any] = {}
        # (target, label) -> the channel's create-stream or cancel of it under way: a
        # command for that stream waits for it to end, then looks again
        self._pending: dict[tuple[str, str], _Pending] = {}
        # anyone on the network may ask who we are: screened on the transport's thread, so
        # a flood costs no task each on the event loop (a second node asks once)
        self._who_lock = threading.Lock()
        self._who_bucket = TokenBucket(IDENTITY_RATE, IDENTITY_RATE, time.monotonic())
        self.identity_shed = 0  # identity queries dropped unanswered, since start
        self._shed_pending = Pending(1.0)  # shed since the last audit record
        self._reports: asyncio.Task[None] | None = None
        # the tasks serving connected commands: asyncio's server does not end them on close
        self._clients: set[asyncio.Task[Any]] = set()
        self._releasing: set[asyncio.Future[None]] = set()  # releases outliving their command

    def _admit_who(self, payload: bytes) -> bool:
        with self._who_lock:
            if self._who_bucket.take(time.monotonic()):
                return True
            self.identity_shed += 1
        self._shed_pending.add()
        return False

    async def _report_shed(self) -> None:
        """Audit the identity queries shed, summed up, at most once per second."""
        while True:
            n = await self._shed_pending.take()  # asleep while nothing is shed
            if n:
                self.platform.interface.audit.record(
                    verdict="dropped",
                    stage="identity-shed",
                    count=n,
                    reason=(
                        f"identity queries shed: {n} dropped unanswered before the event loop "
                        f"(over {IDENTITY_RATE:g}/s, bursts of {IDENTITY_RATE:g})"
                    ),
                )

    async def __aenter__(self) -> LocalChannel:
        config = self.platform.config
        info = json.dumps(_identity(config, self.started)).encode()

        async def who(_key: str, _payload: bytes) -> bytes:
            return info

        key = identity_key(config)
        self._handle = self.platform.agents.declared(
            await self.platform.transport.serve(key, who, admit=self._admit_who),
            f"identity queryable {key}",
            "a second process started as this platform is still refused while its "
            "liveliness token holds, but no longer told where this one runs",
        )
        self._reports = asyncio.get_running_loop().create_task(
            self._report_shed(), name=f"local[{config.name}].identity-shed"
        )
        try:
            _private_dir(self.path.parent)
            # One at a time from the check to the bind: two nodes starting at once must not
            # both find the place free (the second would unlink the first's socket).
            lock_path = self.path.with_name(self.path.name + ".lock")
            try:
                lock = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o600)
            except OSError as exc:
                if exc.errno not in _SHORT_OF:
                    raise
                raise _short_of(exc, f"cannot open the local channel {self.path}") from None
            try:
                await asyncio.to_thread(fcntl.flock, lock, fcntl.LOCK_EX)
                here = await _node_here(self.path)
                if here is not None:  # started since refuse_duplicate looked: never unlinked
                    raise await _alive_error(self.platform.transport, config, here, False)
                # nobody listens on a socket left here: a dead node's
                with contextlib.suppress(FileNotFoundError):
                    self.path.unlink()
                old = os.umask(0o177)
                try:
                    self._server = await asyncio.start_unix_server(
                        self._serve, path=str(self.path), limit=_LINE
                    )
                except OSError as exc:
                    if exc.errno not in _SHORT_OF:
                        raise
                    raise _short_of(exc, f"cannot open the local channel {self.path}") from None
                finally:
                    os.umask(old)
                os.chmod(self.path, 0o600)
                st = self.path.stat()
                self._bound = (st.st_dev, st.st_ino)
            finally:
                os.close(lock)  # and the lock with it
        except BaseException:
            await self.__aexit__()  # not entered: what was set up ends here
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        reports, self._reports = self._reports, None
        if reports is not None:
            reports.cancel()
            await asyncio.wait([reports])
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(TimeoutError):  # a client still connected: do not wait
                async with asyncio.timeout(2.0):
                    await self._server.wait_closed()
        clients = set(self._clients)
        for task in clients:
            task.cancel()  # a command still connected (a stream it follows) ends with the node
        if clients:
            _, pending = await asyncio.wait(clients, timeout=2.0)
            if pending:
                log.warning("local channel: %d command(s) did not end in 2 s", len(pending))
        if self._releasing:  # their exports given back (each cancel takes at most 2 s)
            _, left = await asyncio.wait(set(self._releasing), timeout=2.0)
            for release in left:  # none runs on while the platform closes
                release.cancel()
            if left:
                log.warning("local channel: %d export release(s) cut short", len(left))
                await asyncio.wait(left, timeout=1.0)
        # only the socket this channel bound: not another node's, had it never bound one
        with contextlib.suppress(FileNotFoundError):
            st = self.path.stat()
            if self._bound == (st.st_dev, st.st_ino):
                self.path.unlink()
        if self._handle is not None:
            with contextlib.suppress(TransportError):  # the transport may be closed already
                self._handle.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async def send(obj: Any) -> None:
            writer.write(json.dumps(obj, default=str).encode() + b"\n")
            await writer.drain()

        task = asyncio.current_task()
        if task is not None:
            task.set_name(f"local[{self.platform.name}].command")
            self._clients.add(task)
        try:
            uid = _peer_uid(writer)
            if uid is None or uid not in (os.getuid(), 0):
                # the socket's mode keeps others out; this holds if it was loosened
                self.refused += 1
                log.warning("local channel: refused a client of uid %s", uid)
                # its request is taken (never read) first: closing on a request still on
                # its way would break the client's pipe before it could read the refusal
                with contextlib.suppress(TimeoutError, ValueError):
                    async with asyncio.timeout(_REFUSE_WAIT):
                        await reader.readline()
                await send({"error": "this node serves its own user only"})
                return
            # who we are, before anything is asked: a command of another deployment's
            # config (same names, other key) stops here, its request unsent
            writer.write(self._hello)
            await writer.drain()
            # then the command's nonce, signed back: a key stated proves nothing, a fresh
            # signature by it shows this node holds the config's key
            request = await self._line(reader, send)
            if request is None:
                return
            try:
                nonce = base64.b64decode(request["nonce"], validate=True)
            except (KeyError, TypeError, ValueError):
                await send({"error": "bad request: a nonce to sign comes first"})
                return
            if not 16 <= len(nonce) <= 64:
                await send({"error": "bad request: a nonce of 16 to 64 bytes comes first"})
                return
            proof = self._keys.sign(_proof_data(self.platform.config, nonce))
            await send({"proof": base64.b64encode(proof).decode("ascii")})
            request = await self._line(reader, send)
            if request is None:
                return
            self.served += 1
            try:
                await self._answer(request, send, reader)
            except (ConnectionError, asyncio.IncompleteReadError):
                raise
            except Exception as exc:  # in words, as the command says its own errors
                await send({"error": error_text(exc)})
        except (ConnectionError, asyncio.IncompleteReadError):
            pass  # the command went away (Ctrl-C): its stream is cancelled below
        finally:
            if task is not None:
                self._clients.discard(task)
            writer.close()
            with contextlib.suppress(OSError):  # the peer went: its socket is gone already
                await writer.wait_closed()

    async def _line(
        self, reader: asyncio.StreamReader, send: Callable[[Any], Any]
    ) -> dict[str, Any] | None:
        """The command's next line, a JSON object; None once a bad one was answered."""
        try:
            async with asyncio.timeout(_REQUEST_WAIT):
                line = await reader.readline()
        except TimeoutError:
            await send({"error": f"bad request: none came within {_REQUEST_WAIT:g} s"})
            return None
        except ValueError:  # past the reader's limit (asyncio's LimitOverrunError)
            await send({"error": f"bad request: a line longer than {_LINE} bytes"})
            return None
        try:
            request = json.loads(line)
            if not isinstance(request, dict):
                raise ValueError("not a JSON object")
        except (ValueError, RecursionError) as exc:
            await send({"error": f"bad request: {exc}"})
            return None
        return request

    async def _answer(
        self,
        request: dict[str, Any],
        send: Callable[[Any], Any],
        reader: asyncio.StreamReader,
    ) -> None:

        p = self.platform
        op = request.get("op")
        wait = float(request.get("wait", 3.0))
        timeout = float(request.get("timeout", 10.0))
        if op == "platforms":
            await wait_for_members(p, None, wait)
            await send({"ok": platforms_of(p)})
        elif op == "request":
            target = str(request["platform"])
            async with reaching(p, target, wait):
                answer = await p.federation_agent.request_from(
                    target, request["content"], timeout=timeout
                )
            await send({"ok": answer})
        elif op == "stream":
            await self._stream(request, send, reader, wait, timeout)
        else:
            await send({"error": f"unknown op {op!r}"})

    async def _stream(
        self,
        request: dict[str, Any],
        send: Callable[[Any], Any],
        reader: asyncio.StreamReader,
        wait: float,
        timeout: float,
    ) -> None:
        p = self.platform
        target = str(request["platform"])
        labels = [str(x) for x in request["labels"]]
        sample_period = _sample_period(request.get("sample_period"))
        if target == p.name:
            # the node's own streams: followed in its own instance, as they are made (a
            # platform exports to others only; its local labels by its mapping)
            await self._relay(p, target, labels, request, send, reader, timeout)
            return
        held: list[_Shared] = []  # the channel's exports this command counts in
        try:
            async with reaching(p, target, wait):
                for semantic in labels:
                    entry = await self._acquire(target, semantic, sample_period, timeout)
                    if entry is not None:
                        held.append(entry)
            await self._relay(p, target, labels, request, send, reader, timeout)
        finally:
            await self._release_all(target, held)

    async def _release_all(self, target: str, held: list[_Shared]) -> None:
        """`_release` every entry of ``held``, all of them even when the command is cancelled.

        Each release runs on in its own task if the command is cancelled meanwhile (the
        node stopping): one cut short, or those after it, would leave their exports
        counted for ever and never cancelled. On a cancel the rest start at once, side by
        side, and the cancel goes on up: the channel's end waits for them (bounded).
        """
        for i, entry in enumerate(held):
            try:
                await asyncio.shield(self._start_release(target, entry))
            except asyncio.CancelledError:
                for rest in held[i + 1 :]:
                    self._start_release(target, rest)
                raise

    def _start_release(self, target: str, entry: _Shared) -> asyncio.Future[None]:
        """`_release` ``entry`` in a task of its own, which the channel's end waits for."""
        release = asyncio.ensure_future(self._release(target, entry))
        self._releasing.add(release)
        release.add_done_callback(self._releasing.discard)
        return release

    async def _acquire(
        self, target: str, semantic: str, sample_period: Any, timeout: float
    ) -> _Shared | None:
        """Have ``target``'s ``semantic`` stream imported here, shared by the commands.

        A stream the node imports for its own use (the console's) is followed, never
        created or cancelled from here: None, no count taken. One the channel created is
        shared by the commands following it at once (the first one's sample period) and
        cancelled after the last: its entry, with this command counted in, for `_release`.
        One stream is imported once, at one rate: a command asking for a sample period that
        import does not have is refused (NotAnsweredError says why), never given another
        rate than it asked for. Its create-stream runs outside the lock: a command for
        another stream never waits for it (a platform that does not answer holds it up to
        ``timeout`` s); one for this stream does (`_pending`), then shares what it made,
        or fails with its error: a dead target costs each of them one timeout, not one per
        command before it. Only a cancelled create-stream is asked again.
        """
        p = self.platform
        key = (target, semantic)
        while True:
            async with self._lock:
                # a cancel of this stream on its way, or its create-stream: asked again only
                # once that has ended (the create's outcome is then in `_exports`)
                pending = self._pending.get(key)
                if pending is None:
                    entry = self._exports.get(key)
                    if entry is not None:
                        if sample_period is not None and sample_period != entry.sample_period:
                            had = entry.sample_period
                            rate = "every sample" if had is None else f"--sample-period {had:g}"
                            raise NotAnsweredError(
                                _other_rate(
                                    target, semantic, sample_period, f"another command ({rate})"
                                )
                            )
                        entry.following += 1
                        return entry
                    rec = p.importer.get(target, semantic)
                    mine = rec is not None and rec is self._made.get(key)  # cancelled since
                    if not mine and rec is not None and rec.source is not None and not rec.ended:
                        if sample_period is not None:  # at the rate the node asked for, not ours
                            raise NotAnsweredError(
                                _other_rate(
                                    target,
                                    semantic,
                                    sample_period,
                                    "its own use (the console's streams)",
                                )
                            )
                        return None  # the node's own
                    creating = self._pending[key] = _Pending()
                    break
            await pending.done.wait()
            if pending.error is not None:
                raise pending.error
        # The create-stream runs outside the lock (up to ``timeout`` s for a platform that
        # does not answer): only the commands for this stream wait for it (`_pending`).
        try:
            export_id = await p.federation_agent.create_stream(
                target, [semantic], sample_period=sample_period, timeout=timeout
            )
            # recorded with no await between: a cancel arriving now cannot lose the export
            entry = self._exports[key] = _Shared(export_id, key, sample_period)
            self._made[key] = p.importer.get(target, semantic)
            return entry
        except Exception as error:
            creating.error = error  # the commands waiting on it fail with it too
            raise
        finally:
            # cancelled: a command waiting on it asks again itself
            del self._pending[key]
            creating.done.set()

    async def _release(self, target: str, entry: _Shared) -> None:
        """Take back the count `_acquire` took; the last one out cancels the export.

        The cancel (at most 2 s) runs outside the lock, so commands for other streams do
        not queue behind a dead target; one for this stream waits for it (`_pending`), or
        it would follow the import being cancelled and wait for samples for ever.
        """
        key = entry.key
        async with self._lock:
            entry.following -= 1
            if entry.following > 0 or self._exports.get(key) is not entry:
                return
            del self._exports[key]
            ending = self._pending[key] = _Pending()
        try:
            agent = self.platform.federation_agent
            await agent.cancel_stream(target, entry.export_id, timeout=2.0)
        except Exception as exc:  # the export ends with its lease there anyway
            # the member's words: on one line, bounded
            log.info(
                "local: cancelling the export %s at %s: %s", entry.export_id, target, quoted(exc)
            )
        finally:
            del self._pending[key]
            ending.done.set()

    async def _relay(
        self,
        p: FederationPlatform,
        target: str,
        labels: list[str],
        request: dict[str, Any],
        send: Callable[[Any], Any],
        reader: asyncio.StreamReader,
        timeout: float,
    ) -> None:
        queue: asyncio.Queue[list[Any]] = asyncio.Queue(10_000)

        async def pump(semantic: str) -> None:
            policy = None
            if target == p.name:
                label = p.labels.to_local(semantic)
                # at the rate asked, as an export to another platform would have it
                policy = Policy(sample_period=_sample_period(request.get("sample_period")))
            else:
                try:
                    label = await p.imported(target, semantic, timeout=timeout)
                except TimeoutError as exc:  # an answer not given, said in words
                    raise NotAnsweredError(str(exc)) from None
            sub = p.instance.subscribe(label, policy)
            try:
                if target == p.name:  # bounded as an import's first sample is (`imported`)
                    try:
                        async with asyncio.timeout(timeout):
                            s = await anext(aiter(sub))
                    except TimeoutError:
                        raise NotAnsweredError(
                            f"no sample of {semantic!r} from {target} arrived within {timeout} s"
                        ) from None
                    except StopAsyncIteration:
                        return  # its stream ended first
                    await queue.put([semantic, s.value, s.valid_time, s.available_time])
                async for s in sub:
                    await queue.put([semantic, s.value, s.valid_time, s.available_time])
            finally:
                sub.close()

        count = request.get("count")
        seen = 0
        error: Exception | None = None
        async with asyncio.TaskGroup() as tg:
            pumps = [tg.create_task(failure_of(pump, s), name=f"relay[{s}]") for s in labels]
            # EOF: the command stopped
            gone = tg.create_task(failure_of(reader.read), name="relay.gone")
            try:
                while count is None or seen < int(count):
                    getting = tg.create_task(queue.get(), name="relay.next")
                    done, _ = await asyncio.wait(
                        [getting, gone, *pumps], return_when=asyncio.FIRST_COMPLETED
                    )
                    if getting not in done:
                        getting.cancel()
                        failed = [t.result() for t in pumps if t in done]
                        error = next((e for e in failed if e is not None), None)
                        break
                    await send({"sample": getting.result()})
                    seen += 1
                else:
                    await send({"end": seen})
            except Exception as exc:  # raised below: the group would wrap it
                error = exc
            finally:
                for t in (gone, *pumps):
                    t.cancel()
        if error is not None:
            raise error


def _sample_period(value: Any) -> float | None:
    """A stream request's ``sample_period``: absent, or a finite number of seconds >= 1 ms.

    The node's own streams take the same bound as an export (`RemotePeriod`): a grid
    finer than that, over a gap in the data, fills grid point after grid point.
    """
    if value is None:
        return None
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or value <= 0
    ):
        raise NotAnsweredError(
            f"bad request: sample_period must be a positive number of seconds, not {value!r}"
        )
    if value < MIN_REMOTE_PERIOD:
        raise NotAnsweredError(
            f"bad request: sample_period {value:g} s is under {MIN_REMOTE_PERIOD:g} s, the "
            "finest an export takes"
        )
    return value


def _other_rate(target: str, semantic: str, sample_period: Any, holder: str) -> str:
    """Why a command's ``--sample-period`` cannot apply to a stream imported already."""
    return (
        f"{semantic!r} of platform {target!r} is imported by the running node already, "
        f"for {holder}, and a stream is imported once, at one rate: --sample-period "
        f"{sample_period:g} cannot apply to it. Leave --sample-period out to follow that "
        "import at its rate, or run the command when the node does not import it"
    )


class NodeUnreachable(Exception):
    """No node of this config runs here (no socket, or nobody listening on it)."""


class ForeignNodeError(RuntimeError):
    """The node on this config's channel is not of this config's platform (another key)."""


async def via_node(config: PlatformConfig, request: dict[str, Any]) -> AsyncGenerator[Any, None]:
    """Send ``request`` to the running node of ``config``; its answer lines, decoded.

    NodeUnreachable (before any line) when no node of this config runs on this host;
    LocalChannelError when this host is short of descriptors or memory to tell;
    ForeignNodeError, the request unsent, when the node there states another key or names;
    an ``error`` line, the request unsent, when the node is older than this command.
    """
    keys = _keys_of(config)
    path = channel_path(config, keys)
    # every directory down to the socket ours and closed: else another user could have
    # made the place first and listen there
    if not _private_dir(path.parent, make=False):
        raise NodeUnreachable(f"{path.parent}: no such directory")
    try:
        reader, writer = await asyncio.open_unix_connection(str(path), limit=64 << 20)
    except (FileNotFoundError, ConnectionRefusedError) as exc:
        raise NodeUnreachable(str(exc)) from None
    except OSError as exc:
        if exc.errno in _SHORT_OF:  # this host's lack, not the node's: never "none runs"
            raise _short_of(exc, f"cannot reach the node on its local channel {path}") from None
        raise
    try:
        creds = _peer_cred(writer)
        if creds is None or creds[1] != os.getuid():
            raise ForeignNodeError(_not_ours_listener(path, None if creds is None else creds[1]))
        try:
            async with asyncio.timeout(_HELLO_WAIT):
                first = await reader.readline()
        except TimeoutError:
            raise ForeignNodeError(
                f"the listener on {path} did not say which platform it is in {_HELLO_WAIT:g} s: "
                "not a node of this config; stop it, or remove the socket"
            ) from None
        if not first:
            raise NodeUnreachable(f"{path}: the node closed the channel")
        hello = json.loads(first)
        if isinstance(hello, dict) and "error" in hello:  # refused (another OS user)
            yield hello
            return
        if hello != _hello(config, keys.public_key):
            node = hello.get("node") if isinstance(hello, dict) else None
            raise ForeignNodeError(_foreign(path, config, keys, node))
        nonce = secrets.token_bytes(32)
        writer.write(json.dumps({"nonce": base64.b64encode(nonce).decode("ascii")}).encode())
        writer.write(b"\n")
        await writer.drain()
        try:
            async with asyncio.timeout(_HELLO_WAIT):
                answer = json.loads(await reader.readline())
            older = isinstance(answer, dict) and "error" in answer and "proof" not in answer
            if not older:
                proof = base64.b64decode(answer["proof"], validate=True)
                VerifyKey(keys.public_key).verify(_proof_data(config, nonce), proof)
        except (TimeoutError, ValueError, KeyError, TypeError, BadSignatureError):
            raise ForeignNodeError(
                f"the listener on {path} states this config's key but did not sign this "
                "command's nonce with it: not the node of this config, so nothing was sent "
                "to it; stop it, or remove the socket"
            ) from None
        if older:
            # a node of this config from before the nonce step took the nonce for a bad
            # request: a legitimate node, not one to remove
            yield {
                "error": f"the node on {path} is older than this command (no nonce step; it "
                f"answered: {answer['error']}); restart it with this version"
            }
            return
        writer.write(json.dumps(request).encode() + b"\n")
        await writer.drain()
        while True:
            line = await reader.readline()
            if not line:
                return
            yield json.loads(line)
    finally:
        writer.close()
        with contextlib.suppress(OSError):  # the node went: its socket is gone already
            await writer.wait_closed()


def _foreign(path: Path, config: PlatformConfig, keys: KeyPair, node: Any) -> str:
    """Why the node on ``path`` is not ``config``'s, for the command's user."""
    ours = (
        f"platform {config.name!r} of federation {config.federation!r} "
        f"(key fingerprint {keys.fingerprint})"
    )
    if not isinstance(node, dict):
        return f"the listener on {path} is not a node of {ours}: it did not state its key"
    return (
        f"the node on {path} is platform {node.get('platform')!r} of federation "
        f"{node.get('federation')!r} with key {node.get('ed25519')!r}, not this config's "
        f"{ours}: it runs another deployment, so nothing was sent to it"
    )
