"""A node's own application: its KPL file set up on the platform's instance, fed by inputs.

`check_application` validates the config's ``application`` (KPL file) before anything
opens, with ``FILE:LINE:COL`` errors; `NodeApplication` (an async context manager, inside
an open `FederationPlatform`) sets it up, checks that every fixed input label is a source
and every fixed output label a stream, then runs the inputs and outputs as tasks of the
node. An input that fails later (a broker gone for good, a generator that raises) is
logged and stops alone; the node goes on. See docs/application.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dyknow_core import DyKnowInstance, ProcessFailure

from ._inputs import (
    FileInput,
    InputRunner,
    InputSettings,
    PythonInput,
    Ros2Input,
    RosbagInput,
    input_runner,
)
from ._outputs import MqttOutput, OutputRunner, output_runner
from ._platform import PlatformConfig, PlatformConfigError
from ._quote import quoted

if TYPE_CHECKING:
    from dyknow_core.kpl import KPLApplication

    from ._platform import FederationPlatform

__all__ = ["NodeApplication", "check_application"]

log = logging.getLogger(__name__)

_LOGGED_PER_PROCESS = 5  # a failing unit's first failures logged, then one in _LOG_EVERY
_LOG_EVERY = 1000


def _input_runner(
    settings: InputSettings, instance: DyKnowInstance, starts: dict[Path, tuple[int, int]]
) -> InputRunner:
    """The runner of one ``[[inputs]]`` table: a ROS 2 one from ``_ros``, else ``_inputs``.

    ``starts`` is the node's, shared by its rosbag inputs (`federation._ros.ReplayStarts`).
    """
    if isinstance(settings, Ros2Input | RosbagInput):
        from ._ros import ros_runner  # rosbags and mcap are imported only when used

        return ros_runner(settings, instance, starts)
    return input_runner(settings, instance)


def _application_text(config: PlatformConfig, source: str) -> str | None:
    path = config.application
    if path is None:
        return None
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        raise PlatformConfigError(source, "application", f"{path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise PlatformConfigError(source, "application", f"{path}: not UTF-8: {exc}") from None


def check_application(config: PlatformConfig, source: str) -> None:
    """Check the KPL file, the input files and Python entry points; PlatformConfigError if not.

    KPL errors come as ``FILE:LINE:COL: message`` lines (the form `dyknow kpl check` prints).
    """
    # the KPL modules load only for a node that has an application or Python inputs
    text = _application_text(config, source)
    if text is not None:
        from dyknow_core.kpl import check

        errors = check(text)
        if errors:
            lines = "\n".join(e.format(str(config.application)) for e in errors)
            message = f"the KPL file does not check:\n{lines}"
            raise PlatformConfigError(source, "application", message)
    for n, spec in enumerate(config.inputs):
        # a recording is read once, at start: without it the input could only stop
        if isinstance(spec, FileInput | RosbagInput) and not spec.path.exists():
            raise PlatformConfigError(source, f"inputs[{n}].path", f"{spec.path}: no such file")
    with _importable(config):
        for n, spec in enumerate(config.inputs):
            if isinstance(spec, PythonInput):
                from dyknow_core.kpl import resolve_callable

                module, attr = spec.entry.split(":", 1)
                try:
                    resolve_callable(module, attr)
                except Exception as exc:
                    raise PlatformConfigError(
                        source, f"inputs[{n}].entry", f"{spec.entry}: {type(exc).__name__}: {exc}"
                    ) from None


@contextlib.contextmanager
def _importable(config: PlatformConfig) -> Any:
    """The KPL file's directory first on the import path: its CUs and entry points import."""
    base = str(config.application.parent) if config.application is not None else None
    if base is not None and base not in sys.path:
        sys.path.insert(0, base)
    yield


def in_words(exc: BaseException) -> str:
    """Why an input or output stopped, for its user: the reason, not the Python class."""
    if isinstance(exc, OSError) and exc.strerror:
        where = exc.filename if exc.filename is not None else None
        return exc.strerror.lower() + (f": {where}" if where is not None else "")
    if isinstance(exc, KeyError) and exc.args and type(exc).__str__ is KeyError.__str__:
        # a bare KeyError names only the key; a subclass with its own text says it all
        return f"no {exc.args[0]!r} where one was needed"
    text = str(exc)
    if text:
        return text
    # no message: the exception's name in words (ConnectionResetError: connection reset)
    name = re.sub(r"(Error|Exception)$", "", type(exc).__name__) or type(exc).__name__
    words = re.sub(r"(?<!^)(?=[A-Z])", " ", name).lower()
    return {"timeout": "timed out", "stop iteration": "ended"}.get(words, words)


class NodeApplication:
    """The application, inputs and outputs of one node, set up on an open platform."""

    def __init__(self, platform: FederationPlatform, source: str) -> None:
        self.platform = platform
        self.config = platform.config
        self.source = source
        self.kpl: KPLApplication | None = None
        self.inputs: list[InputRunner] = []
        self.outputs: list[OutputRunner] = []
        self._tasks: list[asyncio.Task[None]] = []
        self._stack: contextlib.AsyncExitStack | None = None  # holds the entered task group
        self._tg: asyncio.TaskGroup | None = None
        self.failures: dict[str, int] = {}  # the application's processes that raised: how often
        self._stop_failures: Any = None

    @property
    def empty(self) -> bool:
        """Whether the config declares nothing to run."""
        c = self.config
        return c.application is None and not c.inputs and not c.outputs

    async def __aenter__(self) -> NodeApplication:
        instance = self.platform.instance
        text = _application_text(self.config, self.source)
        with _importable(self.config):
            if text is not None:
                from dyknow_core.kpl import KPLCheckError, KPLSetupError, setup

                where = str(self.config.application)
                try:
                    self.kpl = setup(instance, text)
                except KPLCheckError as exc:
                    lines = "\n".join(e.format(where) for e in exc.errors)
                    raise PlatformConfigError(self.source, "application", lines) from None
                except KPLSetupError as exc:
                    raise PlatformConfigError(
                        self.source,
                        "application",
                        f"{where}:{exc.line}:{exc.column}: {exc.message}",
                    ) from None
                if self.kpl.processes:
                    self._stop_failures = instance.on_failure(self._failed)
            starts: dict[Path, tuple[int, int]] = {}  # one replay start per recording
            try:
                for spec in self.config.inputs:
                    self.inputs.append(_input_runner(spec, instance, starts))
                self._check(instance)
            except BaseException:
                self._let_go()
                raise
        session = self._zenoh_session()
        async with contextlib.AsyncExitStack() as stack:
            self._tg = await stack.enter_async_context(asyncio.TaskGroup())
            for runner in self.inputs:
                self._start(f"input {runner.stats.title}", runner.run(session))
            for out in self.outputs:
                self._start(f"output {out.settings.title()}", out.run(session))
            self._stack = stack.pop_all()
        return self

    def _check(self, instance: Any) -> None:
        """Make the outputs and check inputs and outputs; PlatformConfigError if one is wrong."""
        self.outputs = [output_runner(s, instance) for s in self.config.outputs]
        for n, runner in enumerate(self.inputs):
            problems = runner.check()
            if problems:
                raise PlatformConfigError(self.source, f"inputs[{n}].fields", problems[0])
        for n, out in enumerate(self.outputs):
            problems = out.check()
            if problems:
                raise PlatformConfigError(self.source, f"outputs[{n}].labels", problems[0])
            problem = out.check_destination()
            if problem is not None:
                field = "topic" if isinstance(out.settings, MqttOutput) else "key"
                raise PlatformConfigError(self.source, f"outputs[{n}].{field}", problem)
        if self._zenoh_session() is None:  # zenoh inputs/outputs need the node's or their own
            for kind, specs in (("inputs", self.config.inputs), ("outputs", self.config.outputs)):
                for n, spec in enumerate(specs):
                    if getattr(spec, "kind", None) in ("zenoh", "ros2") and not getattr(
                        spec, "connect", None
                    ):
                        raise PlatformConfigError(
                            self.source,
                            f"{kind}[{n}].connect",
                            "missing: the node's transport is not zenoh, so this "
                            f"{spec.kind} {kind[:-1]} needs connect = [...] of its own",
                        )

    def _let_go(self) -> None:
        # each input follows the instance's label changes, and the application its
        # failures: one refused or stopped lets go of the instance, which may live on (a
        # library's, a test's)
        if self._stop_failures is not None:
            self._stop_failures()
            self._stop_failures = None
        for runner in self.inputs:
            runner.close()

    def _zenoh_session(self) -> Any | None:
        from agents.transports import ZenohTransport

        transport = self.platform.transport
        return transport.session if isinstance(transport, ZenohTransport) else None

    def _start(self, title: str, coro: Any) -> None:
        assert self._tg is not None
        task = self._tg.create_task(self._logged(title, coro), name=title)
        # cancelled before it ran, the wrapper never awaits ``coro``: close it then
        task.add_done_callback(lambda _: coro.close())
        self._tasks.append(task)

    @staticmethod
    async def _logged(title: str, coro: Any) -> None:
        # one input or output that stops leaves the others running: told, never raised
        try:
            await coro
        except Exception as exc:
            log.error("%s stopped: %s", title, in_words(exc))
        else:
            log.info("%s ended", title)

    def _failed(self, failure: ProcessFailure) -> None:
        # a unit of the user's that raises skips that sample and goes on (docs/core.md):
        # without a word here, a node whose CU fails on every sample would look healthy
        assert self.kpl is not None
        if failure.process not in self.kpl.processes:
            return  # (the platform's own processes say their failures themselves)
        n = self.failures[failure.process] = self.failures.get(failure.process, 0) + 1
        if n <= _LOGGED_PER_PROCESS or n % _LOG_EVERY == 0:
            log.warning(
                "application %s: process %r failed (#%d): %s; that sample is skipped",
                self.config.application,
                failure.process,
                n,
                quoted(failure.error),  # it may quote a value from outside: one line, bounded
            )

    async def __aexit__(self, *exc: object) -> None:
        for task in self._tasks:
            task.cancel()
        stack, self._stack, self._tg = self._stack, None, None
        try:
            if stack is not None:
                await stack.aclose()  # the body's error is not the group's to wrap
        finally:
            self._tasks.clear()
            self._let_go()

    def stats(self) -> list[dict[str, Any]]:
        """What each input received and each output published; the processes that failed."""
        out: list[dict[str, Any]] = []
        if self.failures:
            out.append({"application": str(self.config.application), "failed": self.failures})
        out += [r.stats.as_dict() for r in self.inputs]
        out += [
            {
                "output": o.settings.title(),
                "published": o.published,
                "dropped": o.dropped,
                "refused": o.refused,
            }
            for o in self.outputs
        ]
        return out
