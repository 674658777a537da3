"""The compose topology on loopback, without Docker or root: ``up``, ``down``, ``status``.

A zenoh router on 127.0.0.1, uav-a/b/c (each running its application, fed by the traffic
world) and the operator with the web console, as local processes run by honcho (a
Procfile runner). ``up`` makes the keys on first use, writes the loopback configs (from
``deploy/config/``) and the Procfile into the run directory, starts honcho in the
background, and returns once every platform said it is ready (exit 0, the console's URL
printed); a service that cannot start fails it, named, with its last log lines (exit 1,
everything stopped). ``down`` stops honcho, which stops every service. Both are
idempotent. Settings (environment): DYKNOW_LOCAL_RUN (the run directory, default
deploy/local/run), DYKNOW_LOCAL_ROUTER_PORT (17447), DYKNOW_LOCAL_CONSOLE_PORT (18080),
DYKNOW_LOCAL_TIMEOUT (seconds ``up`` waits, 90), DYKNOW_LOCAL_WORLD_SPEED (the traffic
world's simulated seconds per second, 1: a faster replay). See deploy/README.md.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEPLOY = HERE.parent
ROOT = DEPLOY.parent
PY = sys.executable
SERVICES = ("router", "uav-a", "uav-b", "uav-c", "operator")
PLATFORMS = ("uav-a", "uav-b", "uav-c", "operator")
READY = {
    "router": "dyknow router: zid",
    **{p: f"dyknow node: {p} ready" for p in ("uav-a", "uav-b", "uav-c")},
    "operator": "dyknow console: operator ready",
}
_LINE = re.compile(r"^\S+ (?P<name>[\w.-]+?)(?:\.1)?\s+\| (?P<text>.*)$")
# the world feed's arguments in deploy/config/uav-*.toml, where a speed goes
_FEED_ARGS = re.compile(r'^(args = \{uav = "uav-\w", seed = \d+)\}$', re.MULTILINE)
# the application's times (traffic-app.kpl), seconds of the messages' times, which a
# faster world runs through sooner: the monitor's always[a,b], the chronicles' "in [a, b]",
# every period and max_delay
_WINDOW = re.compile(r"(always\[|in \[)([\d.]+),\s*([\d.]+)\]")
_PERIOD = re.compile(r"\b(every|max_delay) ([\d.]+)\b")
FEED_PERIOD = 0.2  # s between two frames of the world feed at 1x (its default)


def _settings() -> tuple[Path, int, int, float]:
    run = Path(os.environ.get("DYKNOW_LOCAL_RUN", HERE / "run")).resolve()
    router = int(os.environ.get("DYKNOW_LOCAL_ROUTER_PORT", "17447"))
    console = int(os.environ.get("DYKNOW_LOCAL_CONSOLE_PORT", "18080"))
    timeout = float(os.environ.get("DYKNOW_LOCAL_TIMEOUT", "90"))
    return run, router, console, timeout


def _world_speed() -> float:
    """DYKNOW_LOCAL_WORLD_SPEED: the traffic world's simulated seconds per second (1)."""
    text = os.environ.get("DYKNOW_LOCAL_WORLD_SPEED", "1")
    try:
        speed = float(text)
    except ValueError:
        speed = math.nan
    if not (math.isfinite(speed) and speed > 0):
        raise SystemExit(
            f"deploy/local: DYKNOW_LOCAL_WORLD_SPEED must be a positive number, not {text!r}"
        )
    return speed


def _say(text: str) -> None:
    print(text, flush=True)


def _configs(run: Path, router: int, speed: float = 1.0) -> Path:
    """deploy/config's files in ``run/config``, the router on 127.0.0.1:``router``.

    ``speed``: the traffic world's, given to each UAV's world feed; the feed's period and
    the application's times (windows, periods) shrink by as much: the application sees
    the world as at 1x, in less time.
    """
    config = run / "config"
    config.mkdir(parents=True, exist_ok=True)
    src = DEPLOY / "config"
    for f in [*src.glob("*.toml"), *src.glob("*.kpl")]:
        text = f.read_text(encoding="utf-8")
        text = text.replace('"tcp/172.28.0.10:7447"', f'"tcp/127.0.0.1:{router}"')
        text = text.replace("(docker-compose.yml)", "(deploy/local)")
        if speed != 1.0 and re.fullmatch(r"uav-\w\.toml", f.name):
            args = rf"\1, speed = {speed!r}, period = {FEED_PERIOD / speed!r}}}"
            text, n = _FEED_ARGS.subn(args, text)
            if n != 1:  # the config changed shape: say so rather than run at 1x
                raise SystemExit(f"deploy/local: no world feed's args in {f} to set the speed in")
        if speed != 1.0 and f.suffix == ".kpl":
            text = _WINDOW.sub(
                lambda m: f"{m[1]}{float(m[2]) / speed:g}, {float(m[3]) / speed:g}]", text
            )
            text = _PERIOD.sub(lambda m: f"{m[1]} {float(m[2]) / speed:g}", text)
        (config / f.name).write_text(text, encoding="utf-8")
    return config


def _keys(config: Path) -> None:
    """Every platform's key pair and the trust file, made on first use (make-keys.sh)."""
    keys = config / "keys"
    if all((keys / f"{p}.key").exists() for p in PLATFORMS) and (keys / "trust.json").exists():
        return
    env = {**os.environ, "PYTHON": PY}
    done = subprocess.run(
        ["bash", str(DEPLOY / "make-keys.sh"), str(config)],
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise SystemExit(f"deploy/local: making the keys failed:\n{done.stdout}{done.stderr}")


def _procfile(run: Path, router: int, console: int) -> Path:
    cli = f"{PY} -m federation.cli"
    wait = f"{PY} {HERE / 'local.py'} wait-port {router}"
    lines = [f"router: exec {cli} router --listen tcp/127.0.0.1:{router}"]
    for uav in ("uav-a", "uav-b", "uav-c"):
        lines.append(f"{uav}: {wait} && exec {cli} node --config config/{uav}.toml")
    lines.append(
        f"operator: {wait} && exec {cli} console --config config/operator.toml"
        f" --host 127.0.0.1 --port {console}"
    )
    path = run / "Procfile"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _honcho_pid(run: Path) -> int | None:
    """The running honcho's pid (None: not running; a stale pid file is removed)."""
    pidfile = run / "honcho.pid"
    try:
        pid = int(pidfile.read_text().strip())
    except (OSError, ValueError):
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        pidfile.unlink(missing_ok=True)
        return None
    return pid


def _log(run: Path) -> list[tuple[str, str]]:
    """(service, text) of every line honcho wrote."""
    out = []
    try:
        text = (run / "honcho.log").read_text(encoding="utf-8", errors="replace")
    except OSError:
        return out
    for line in text.splitlines():
        m = _LINE.match(line)
        if m:
            out.append((m.group("name"), m.group("text")))
    return out


def _state(run: Path) -> tuple[dict[str, str], str | None]:
    """Services ready (with their ready line), and the first that stopped (or None)."""
    ready: dict[str, str] = {}
    stopped = None
    for name, text in _log(run):
        if name in READY and text.startswith(READY[name]):
            ready[name] = text
        if name == "system":
            m = re.match(r"([\w-]+)\.1 stopped", text)
            if m and stopped is None:
                stopped = m.group(1)
    return ready, stopped


def _url(ready: dict[str, str]) -> str:
    return ready.get("operator", "").rsplit(": ", 1)[-1].strip()


def _honcho() -> list[str]:
    exe = Path(PY).parent / "honcho"
    return [str(exe)] if exe.exists() else [PY, "-m", "honcho"]


def up() -> int:
    """Start everything (or find it running); exit 0 once every platform is ready."""
    run, router, console, timeout = _settings()
    speed = _world_speed()
    run.mkdir(parents=True, exist_ok=True)
    if _honcho_pid(run) is not None:
        ready, stopped = _state(run)
        if set(ready) == set(SERVICES) and stopped is None:
            _say(f"deploy/local: already up; the console: {_url(ready)}")
            return 0
        down()  # half up: start again from nothing
    config = _configs(run, router, speed)
    _keys(config)
    procfile = _procfile(run, router, console)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    path = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    env["PYTHONPATH"] = path  # the checkout's code, also when not installed
    with (run / "honcho.log").open("wb") as log:
        proc = subprocess.Popen(
            [*_honcho(), "--no-colour", "-f", str(procfile), "-d", str(run), "start"],
            cwd=run,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # on its own: the shell that ran `up` may go
        )
    (run / "honcho.pid").write_text(f"{proc.pid}\n")
    deadline = time.monotonic() + timeout
    while True:
        ready, stopped = _state(run)
        if stopped is not None or proc.poll() is not None:
            name = stopped or "honcho"
            _fail(run, name, f"{name} stopped before every platform was ready")
            return 1
        if set(ready) == set(SERVICES):
            break
        if time.monotonic() > deadline:
            waiting = ", ".join(s for s in SERVICES if s not in ready)
            _fail(run, waiting, f"not ready within {timeout:.0f} s: {waiting}")
            return 1
        time.sleep(0.2)  # honcho's log is a file: nothing to await
    _say(f"deploy/local: up (router 127.0.0.1:{router}, uav-a, uav-b, uav-c, operator)")
    _say(
        f"deploy/local: configs in {config}; e.g. .venv/bin/dyknow ask car2-state -p uav-a "
        f"--config {config / 'operator.toml'}"
    )
    _say(f"deploy/local: the console: {_url(ready)}")
    return 0


def _fail(run: Path, names: str, why: str) -> None:
    print(f"deploy/local: up failed: {why}", file=sys.stderr, flush=True)
    wanted = set(names.split(", "))
    lines = [f"  {n} | {t}" for n, t in _log(run) if n in wanted]
    if lines:
        print(f"deploy/local: the last lines of {names}:", file=sys.stderr)
        print("\n".join(lines[-15:]), file=sys.stderr, flush=True)
    print(f"deploy/local: the whole log: {run / 'honcho.log'}", file=sys.stderr, flush=True)
    down(quiet=True)


def _children(run: Path, exclude: str | None = None) -> list[int]:
    """The pids honcho says it started (each leads its own process group)."""
    pids = []
    for name, text in _log(run):
        m = re.match(r"([\w-]+)\.1 started \(pid=(\d+)\)", text) if name == "system" else None
        if m and m.group(1) != exclude:
            pids.append(int(m.group(2)))
    return pids


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def down(quiet: bool = False) -> int:
    """Stop honcho and, through it, every service; nothing running is fine."""
    run, *_ = _settings()
    pid = _honcho_pid(run)
    if pid is None:
        if not quiet:
            _say("deploy/local: nothing running")
        return 0
    # The platforms first, while the router still carries their goodbyes (a platform
    # leaving through a gone router waits for zenoh's timeouts); then honcho, which stops
    # the rest and SIGKILLs what has not stopped 5 s later.
    platforms = _children(run, exclude="router")
    for child in platforms:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(child, signal.SIGTERM)
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and any(_alive(c) for c in platforms):
        time.sleep(0.1)
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)
        time.sleep(0.1)
    else:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(pid, signal.SIGKILL)
    for child in _children(run):  # honcho's own record of what it started
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(child, signal.SIGKILL)
    (run / "honcho.pid").unlink(missing_ok=True)
    if not quiet:
        _say("deploy/local: down")
    return 0


def status() -> int:
    """Which services are ready (exit 0 when all are)."""
    run, *_ = _settings()
    if _honcho_pid(run) is None:
        _say("deploy/local: not running")
        return 3
    ready, stopped = _state(run)
    for s in SERVICES:
        _say(f"{s}: {'ready' if s in ready else 'starting'}")
    return 0 if set(ready) == set(SERVICES) and stopped is None else 1


def wait_port(port: int, timeout: float = 30.0) -> int:
    """Wait until 127.0.0.1:``port`` accepts connections (the router, before the nodes)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError):
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return 0
        time.sleep(0.1)
    print(f"deploy/local: nothing listens on 127.0.0.1:{port} after {timeout} s", file=sys.stderr)
    return 1


def main(argv: list[str]) -> int:
    """``up``, ``down``, ``status`` or ``wait-port PORT``."""
    if argv[:1] == ["up"]:
        return up()
    if argv[:1] == ["down"]:
        return down()
    if argv[:1] == ["status"]:
        return status()
    if argv[:1] == ["wait-port"] and len(argv) == 2:
        return wait_port(int(argv[1]))
    print("usage: local.py up|down|status", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
