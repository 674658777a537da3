"""``dyknow node``: its option and its run, importable without typer.

A node is the process a platform keeps running, and what it imports it holds for its
whole life. So the ``dyknow`` entry (``federation.cli``) runs ``dyknow node -c FILE``
from here, without loading typer and the other commands; every other command line,
``--help`` and mistakes included, goes to the typer app (``federation._cli_app``), whose
``node`` command is built from the same option (`CONFIG_FLAGS`, `CONFIG_HELP`) and runs
the same `run_node`. `node_config` takes only the plainest spellings of that option and
leaves the rest to typer, so the two cannot read one command line differently.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import sys
import types
from collections.abc import Iterator, Sequence
from importlib.machinery import PathFinder
from pathlib import Path
from typing import TextIO

# the --config/-c of every command (a platform's TOML config), `dyknow node`'s only option
CONFIG_FLAGS = ("--config", "-c")
CONFIG_HELP = "the platform's TOML config"
# the variable by which a shell asks the ``dyknow`` command (click, under typer) to complete
COMPLETE_VAR = "_DYKNOW_COMPLETE"


# a log record on a long-running command's stderr: its level and logger say what it is,
# apart from the command's own lines ("dyknow node: …")
LOG_FORMAT = "%(levelname)s %(name)s: %(message)s"
# Python's own last resort (bare messages to stderr), whatever the process made of it since
_PYTHONS_LAST_RESORT = getattr(logging, "_defaultLastResort", logging.lastResort)
# paho's ERRORs (logger "mqtt", aiomqtt's) on a connection that failed under it: the MQTT
# transport says that loss itself, once, at WARNING ("connection to the broker lost …"),
# and ends or reconnects; printed too, they read as a second, rawer fault
_PAHO_SOCKET_ERRORS = frozenset({"failed to receive on socket: %s", "timeout on socket: %s"})


@contextlib.contextmanager
def log_to_stderr() -> Iterator[None]:
    """While in it, have the log's warnings and errors go to stderr as ``LEVEL logger: message``.

    Without it Python's last resort printed the bare message: an ERROR looked like a
    WARNING and like the command's own lines. It becomes that last resort, so it prints
    only what no handler of the process takes: a caller that configured its logging (on
    the root or only on a logger such as ``agents``) gets its records once, its own way.
    A last resort the process chose already (None included) is left alone; on leaving,
    the one found is given back (a program embedding `run_node` goes on with its own),
    unless the process chose another meanwhile.
    """
    found = logging.lastResort
    if found is not _PYTHONS_LAST_RESORT:
        yield
        return
    handler = _Stderr()
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    logging.lastResort = handler
    try:
        yield
    finally:
        if logging.lastResort is handler:
            logging.lastResort = found


def _not_said_twice(record: logging.LogRecord) -> bool:
    """False for a record whose news the command's own lines say already (paho's on a
    connection lost: the transport's warning says it)."""
    msg = record.msg
    return not (record.name == "mqtt" and type(msg) is str and msg in _PAHO_SOCKET_ERRORS)


class _Stderr(logging.StreamHandler):
    """Warnings and errors to the ``sys.stderr`` of the moment, as Python's last resort.

    Not the one when it was made: a caller that ran the command with its stderr captured
    (a test runner) would lose every later record to a capture long gone.
    """

    def __init__(self) -> None:
        logging.Handler.__init__(self, logging.WARNING)
        self.addFilter(_not_said_twice)

    @property
    def stream(self) -> TextIO:
        """The current ``sys.stderr``."""
        return sys.stderr


def say(text: str) -> None:
    """Print one line to stdout, flushed (a supervisor may be reading)."""
    print(text, flush=True)


def node_config(args: Sequence[str]) -> Path | None:
    """The config of ``node -c FILE`` / ``--config FILE`` / ``--config=FILE``; else None.

    None means typer parses ``args``: anything else (help, a missing or option-looking
    value, another command, a shell-completion request in the environment) gets typer's
    own answer.
    """
    if COMPLETE_VAR in os.environ:  # typer reads this before the command line
        return None
    if len(args) == 3 and args[0] == "node" and args[1] in CONFIG_FLAGS:
        value = args[2]
    elif len(args) == 2 and args[0] == "node" and args[1].startswith(CONFIG_FLAGS[0] + "="):
        value = args[1].partition("=")[2]
    else:
        return None
    return Path(value) if value and not value.startswith("-") else None


def _fail(message: str, code: int = 2) -> int:
    """Print ``message`` on stderr; the exit code to return."""
    print(message, file=sys.stderr, flush=True)
    return code


# pydantic's plugin loader, which it imports at the first validator it builds
_PLUGIN_LOADER = "pydantic.plugin._loader"


def no_pydantic_plugins() -> bool:
    """Whether no installed distribution declares a pydantic plugin; False when unsure.

    Looks where ``importlib.metadata.entry_points`` would (each directory on ``sys.path``,
    its ``*.dist-info`` and ``*.egg-info``), for any ``entry_points.txt`` that names
    pydantic at all; anything it cannot read as plainly (a zip or an egg on the path,
    another finder of distributions, an unreadable entry) counts as a plugin.
    """
    if any(
        getattr(finder, "find_distributions", None) is not None and finder is not PathFinder
        for finder in sys.meta_path
    ):
        return False
    for entry in sys.path:
        root = entry or "."
        if root.lower().endswith(".egg"):
            return False
        try:
            with os.scandir(root) as children:
                names = [child.name for child in children]
        except FileNotFoundError:  # nothing there, for importlib.metadata neither
            continue
        except OSError:  # a zip file, or a directory we may not list
            return False
        for name in names:
            if not name.lower().endswith((".dist-info", ".egg-info")):
                continue
            try:
                text = Path(root, name, "entry_points.txt").read_bytes()
            except (FileNotFoundError, NotADirectoryError):  # no entry points
                continue
            except OSError:
                return False
            if b"pydantic" in text:
                return False
    return True


def skip_pydantic_plugin_scan() -> bool:
    """Spare pydantic its plugin search when no distribution declares one; whether spared.

    pydantic imports ``importlib.metadata`` and reads every installed distribution's
    entry points at the first validator it builds (~15-20 ms of a node's start): when
    `no_pydantic_plugins`, its loader is replaced by one that finds none, which is what
    the search would find. Installed plugins are searched for and loaded as ever.
    """
    if _PLUGIN_LOADER in sys.modules or not no_pydantic_plugins():
        return False
    import pydantic.plugin

    loader = types.ModuleType(_PLUGIN_LOADER, "pydantic's plugin loader, no plugin installed")
    plugins: dict[str, object] = {}
    vars(loader).update(
        PYDANTIC_ENTRY_POINT_GROUP="pydantic",
        _plugins=plugins,
        _loading_plugins=False,
        get_plugins=plugins.values,
    )
    sys.modules[_PLUGIN_LOADER] = loader
    pydantic.plugin._loader = loader  # type: ignore[attr-defined]  # as an import sets it
    return True


def run_node(config: Path) -> int:
    """Run one platform from its TOML config until SIGINT/SIGTERM; the exit code.

    2: the config is wrong, the platform runs already, or its local channel's place is
    another user's; 1: the transport failed, or ended one of the platform's declarations
    (the node stopped cleanly first: `PlatformLostError`), or the host lacks what the
    local channel takes (file descriptors). The log goes to stderr while it runs
    (`log_to_stderr`).
    """
    with log_to_stderr():
        return _run_node(config)


def _run_node(config: Path) -> int:
    """`run_node`'s run, its log set up."""
    # What the imports build lives as long as the node: the cyclic GC would walk it again
    # and again until ready (~15 ms of a node's start), so it is off while they run and
    # what they built is frozen out of its sight; once ready, `settle_gc` collects it all
    collecting = gc.isenabled()
    gc.disable()
    try:
        skip_pydantic_plugin_scan()
        from agents import TransportError, run

        from ._cli_net import run_node as serve
        from ._local import ForeignNodeError, LocalChannelError, PlatformAliveError
        from ._platform import PlatformConfig, PlatformConfigError

        gc.freeze()
    finally:
        if collecting:  # as the caller had it (an in-process caller may have it off)
            gc.enable()
    try:
        cfg = PlatformConfig.load(config)
        run(serve(cfg, str(config), say))
    except PlatformConfigError as exc:
        return _fail(str(exc))
    except (PlatformAliveError, ForeignNodeError) as exc:
        return _fail(f"dyknow node: {config}: {exc}")
    except (TransportError, LocalChannelError) as exc:
        return _fail(f"dyknow node: {config}: {exc}", 1)
    finally:
        # the node has ended: a caller that goes on (a test calling the entry point) gets
        # its objects back in the collector's sight, a node that never got ready included
        gc.unfreeze()
    return 0
