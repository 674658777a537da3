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
import sys
from typing import TYPE_CHECKING, Any

from ._inputs import InputRunner, PythonInput, input_runner
from ._outputs import OutputRunner, output_runner
from ._platform import PlatformConfig, PlatformConfigError

if TYPE_CHECKING:
    from dyknow_core.kpl import KPLApplication

    from ._platform import FederationPlatform

__all__ = ["NodeApplication", "check_application"]

log = logging.getLogger(__name__)


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
    """Check the KPL file and the Python entry points; PlatformConfigError listing each problem.

    KPL errors come as ``FILE:LINE:COL: message`` lines (the form `dyknow kpl check` prints).
    """
    from dyknow_core.kpl import check, resolve_callable

    text = _application_text(config, source)
    if text is not None:
        errors = check(text)
        if errors:
            lines = "\n".join(e.format(str(config.application)) for e in errors)
            message = f"the KPL file does not check:\n{lines}"
            raise PlatformConfigError(source, "application", message)
    with _importable(config):
        for n, spec in enumerate(config.inputs):
            if isinstance(spec, PythonInput):
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

    @property
    def empty(self) -> bool:
        """Whether the config declares nothing to run."""
        c = self.config
        return c.application is None and not c.inputs and not c.outputs

    async def __aenter__(self) -> NodeApplication:
        from dyknow_core.kpl import KPLCheckError, KPLSetupError, setup

        instance = self.platform.instance
        text = _application_text(self.config, self.source)
        with _importable(self.config):
            if text is not None:
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
            self.inputs = [input_runner(s, instance) for s in self.config.inputs]
            self.outputs = [output_runner(s, instance) for s in self.config.outputs]
            for n, runner in enumerate(self.inputs):
                problems = runner.check()
                if problems:
                    raise PlatformConfigError(self.source, f"inputs[{n}].fields", problems[0])
            for n, out in enumerate(self.outputs):
                problems = out.check()
                if problems:
                    raise PlatformConfigError(self.source, f"outputs[{n}].labels", problems[0])
        session = self._zenoh_session()
        if session is None:  # zenoh inputs/outputs need the node's session or their own
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
        for runner in self.inputs:
            self._start(runner.stats.title, runner.run(session))
        for out in self.outputs:
            self._start(f"output {out.settings.title()}", out.run(session))
        return self

    def _zenoh_session(self) -> Any | None:
        from agents.transports import ZenohTransport

        transport = self.platform.transport
        return transport.session if isinstance(transport, ZenohTransport) else None

    def _start(self, title: str, coro: Any) -> None:
        task = asyncio.create_task(coro, name=title)
        task.add_done_callback(lambda t: self._ended(title, t))
        self._tasks.append(task)

    @staticmethod
    def _ended(title: str, task: asyncio.Task[None]) -> None:
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:
            log.error("%s stopped: %s: %s", title, type(exc).__name__, exc)
        else:
            log.info("%s ended", title)

    async def __aexit__(self, *exc: object) -> None:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()

    def stats(self) -> list[dict[str, Any]]:
        """What each input received and each output published."""
        out = [r.stats.as_dict() for r in self.inputs]
        out += [
            {"output": o.settings.title(), "published": o.published, "dropped": o.dropped}
            for o in self.outputs
        ]
        return out
