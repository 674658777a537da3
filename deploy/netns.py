#!/usr/bin/env python3
"""The zenoh topology of docker-compose.yml for real on one Linux machine, in network namespaces.

One namespace per service (router, uav-a, uav-b, uav-c, operator), each with its own
address on a private /24, all joined by a bridge that lives in a namespace of its own
(``<prefix>-net``). Nothing is added to the machine's own namespace: no link, no address,
no route, so several runs (even with the same subnet) cannot see each other or the
machine's network. Every platform is a zenoh client of the router, exactly as in compose:
the authenticated router (mutual TLS with a CA made for the run, passwords, access control)
and the platforms' ``config/secure/*.toml``, their addresses and paths rewritten.

    sudo .venv/bin/python deploy/netns.py up --dir /tmp/dk       # namespaces, keys, processes
    sudo .venv/bin/python deploy/netns.py check --dir /tmp/dk    # the operator sees the UAVs
    sudo .venv/bin/python deploy/netns.py status --dir /tmp/dk
    sudo .venv/bin/python deploy/netns.py down --dir /tmp/dk     # or: down --prefix dk1234
    sudo .venv/bin/python deploy/netns.py run --dir /tmp/dk      # up, check, down

Needs root and iproute2's ``ip``; without them it says so and exits 2. Exit 1: a step
failed (the message says which); ``up`` cleans up what it made before exiting.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
HERE = ROOT / "deploy"
CONFIG = HERE / "config"
PLATFORMS = ("uav-a", "uav-b", "uav-c", "operator")
SERVICES = ("router", *PLATFORMS)
HOSTS = {"router": 10, "uav-a": 11, "uav-b": 12, "uav-c": 13, "operator": 20}
PORT = 7447
FEDERATION = "traffic"
SWITCH = "net"  # the namespace holding the bridge: <prefix>-net
STATE = "netns.json"
# What deploy/config/secure/*.toml and router-secure.json5 say for the compose network
# (the authenticated router: mutual TLS, passwords, access control); replaced here.
COMPOSE_CONNECT = "tls/172.28.0.10:7447"
COMPOSE_LISTEN = '"tls/0.0.0.0:7447"'
COMPOSE_TLS = "/etc/dyknow/tls/"
_PREFIX = re.compile(r"^[a-z][a-z0-9]{0,11}$")


class Failure(Exception):
    """A step that failed: the message for the user, and the exit code."""

    def __init__(self, message: str, code: int = 1) -> None:
        super().__init__(message)
        self.code = code


def say(text: str) -> None:
    """One progress line on stdout, flushed (a test or a supervisor may be reading)."""
    print(f"netns: {text}", flush=True)


# -- names, addresses, prerequisites ------------------------------------------------------------


def namespace(prefix: str, service: str) -> str:
    """The namespace name of one service (or of the switch) in run ``prefix``."""
    return f"{prefix}-{service}"


def address(subnet: str, service: str) -> str:
    """The service's IPv4 address in ``subnet`` (three octets, e.g. ``10.231.0``)."""
    return f"{subnet}.{HOSTS[service]}"


def check_prefix(prefix: str) -> str:
    """``prefix`` if usable in namespace names, else a Failure naming the rule."""
    if not _PREFIX.match(prefix):
        raise Failure(
            f"--prefix {prefix!r}: use 1-12 lowercase letters and digits, starting with a letter",
            2,
        )
    return prefix


def check_subnet(subnet: str) -> str:
    """``subnet`` if it is three octets of a private /24 (e.g. ``10.231.0``), else a Failure."""
    try:
        net = ipaddress.IPv4Network(f"{subnet}.0/24")
    except ValueError:
        net = None
    if net is None or subnet.count(".") != 2 or not net.is_private:
        raise Failure(f"--subnet {subnet!r}: give three octets of a private /24, e.g. 10.231.0", 2)
    return subnet


def check_prerequisites() -> None:
    """Root and ``ip`` are needed: a Failure with exit code 2 saying which is missing."""
    if shutil.which("ip") is None:
        raise Failure("the `ip` command (iproute2) is not installed: apt-get install iproute2", 2)
    if os.geteuid() != 0:
        raise Failure("network namespaces need root: run this as root (e.g. with sudo)", 2)


def ip(*args: str, check: bool = True) -> str:
    """Run ``ip ARGS``; its stdout, or a Failure quoting the command and ip's message."""
    proc = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=False)
    if check and proc.returncode != 0:
        raise Failure(f"`ip {' '.join(args)}` failed: {proc.stderr.strip() or proc.returncode}")
    return proc.stdout


def namespaces_of(prefix: str) -> list[str]:
    """The namespaces of run ``prefix`` that exist now (switch last)."""
    names = {line.split()[0] for line in ip("netns", "list").splitlines() if line.strip()}
    ours = [namespace(prefix, s) for s in (*SERVICES, SWITCH)]
    return [n for n in ours if n in names]


def free_prefix() -> str:
    """``dk<pid>``, or with a letter appended if a run already uses that (pids are reused)."""
    for suffix in ("", *"abcdefghijklmnopqrstuvwxyz"):
        prefix = f"dk{os.getpid()}{suffix}"
        if not namespaces_of(prefix):
            return prefix
    raise Failure(f"dk{os.getpid()}[a-z] are all in use: give --prefix")


# -- the network --------------------------------------------------------------------------------


def make_network(prefix: str, subnet: str) -> None:
    """The switch namespace with its bridge, and one namespace per service wired to it."""
    switch = namespace(prefix, SWITCH)
    try:
        ip("netns", "add", switch)
    except Failure as exc:
        raise Failure(f"cannot create a network namespace here: {exc}", 2) from None
    ip("-n", switch, "link", "add", "br0", "type", "bridge")
    ip("-n", switch, "link", "set", "br0", "up")
    for service in SERVICES:
        ns = namespace(prefix, service)
        say(f"namespace {ns}: {address(subnet, service)}/24 on eth0, bridged in {switch}")
        ip("netns", "add", ns)
        ip("-n", ns, "link", "set", "lo", "up")
        # Both ends are created inside our namespaces: the machine's own sees no new link.
        port = f"v-{service}"
        ip("-n", switch, "link", "add", port, "type", "veth", "peer", "name", "eth0", "netns", ns)
        ip("-n", switch, "link", "set", port, "master", "br0", "up")
        ip("-n", ns, "addr", "add", f"{address(subnet, service)}/24", "dev", "eth0")
        ip("-n", ns, "link", "set", "eth0", "up")


# -- configs and keys ---------------------------------------------------------------------------


def _replaced(text: str, old: str, new: str, source: Path) -> str:
    """``text`` with ``old`` replaced by ``new``; a Failure if ``source`` no longer has it."""
    if old not in text:
        raise Failure(f"{source}: expected {old} in it (the compose address) to replace")
    return text.replace(old, new)


def write_configs(rundir: Path, subnet: str) -> None:
    """Keys, trust file, vocabulary, mappings and configs for this topology into ``rundir``."""
    sys.path.insert(0, str(ROOT))
    from agents.keys import KeysError, gen_keys, trust_keys
    from federation import PlatformConfig, PlatformConfigError

    keys = rundir / "keys"
    try:
        pubs = [gen_keys(p, keys, force=True)[2] for p in PLATFORMS]
        (keys / "trust.json").unlink(missing_ok=True)
        trust_keys(keys / "trust.json", pubs, federation=FEDERATION)
    except KeysError as exc:
        raise Failure(f"keys: {exc}") from None
    shutil.copy(CONFIG / "traffic.toml", rundir / "traffic.toml")
    shutil.copy(CONFIG / "traffic-app.kpl", rundir / "traffic-app.kpl")  # the UAVs' application
    # the zenoh links' certificates, from a CA of this run: the router's names its address
    tls = rundir / "tls"
    certs = [sys.executable, str(HERE / "make_certs.py"), "--dir", str(tls)]
    certs += [f"--platform={p}" for p in PLATFORMS]
    certs += [f"--router-name={address(subnet, 'router')}"]
    made = subprocess.run(certs, capture_output=True, text=True, timeout=60, check=False)
    if made.returncode != 0:
        raise Failure(f"make_certs.py: {made.stderr.strip() or made.stdout.strip()}")
    router = f"tls/{address(subnet, 'router')}:{PORT}"
    for platform in PLATFORMS:
        shutil.copy(CONFIG / f"{platform}-labels.toml", rundir / f"{platform}-labels.toml")
        source = CONFIG / "secure" / f"{platform}.toml"
        path = rundir / f"{platform}.toml"
        text = _replaced(source.read_text(), COMPOSE_CONNECT, router, source)
        text = _replaced(text, COMPOSE_TLS, f"{tls}/", source)
        # the secure configs sit one directory below their files; these next to them
        path.write_text(_replaced(text, '"../', '"', source))
        try:
            PlatformConfig.load(path)
        except PlatformConfigError as exc:
            raise Failure(str(exc)) from None
    source = CONFIG / "router-secure.json5"
    text = _replaced(source.read_text(), COMPOSE_LISTEN, f'"{router}"', source)
    (rundir / "router.json5").write_text(_replaced(text, COMPOSE_TLS, f"{tls}/", source))
    say(f"keys, trust file, certificates and configs for {subnet}.0/24 written to {rundir}")


# -- processes ----------------------------------------------------------------------------------


def command(service: str, rundir: Path, subnet: str) -> list[str]:
    """The ``dyknow`` command line of one service (run inside its namespace)."""
    if service == "router":
        # --listen as well: `dyknow router --zenoh-config` alone listens on an ephemeral loopback
        # port, not on the config's endpoints (ZenohConfig.to_zenoh overrides them).
        listen = f"tls/{address(subnet, 'router')}:{PORT}"
        return ["router", "--zenoh-config", str(rundir / "router.json5"), "--listen", listen]
    return ["node", "--config", str(rundir / f"{service}.toml")]


def in_namespace(ns: str, args: Sequence[str]) -> list[str]:
    """``python -m federation.cli ARGS`` inside namespace ``ns`` (this interpreter, the repo)."""
    return ["ip", "netns", "exec", ns, sys.executable, "-m", "federation.cli", *args]


def ready_line(service: str) -> str:
    """The start of the line a service prints once it is up."""
    if service == "router":
        return "dyknow router: zid "
    return f"dyknow node: {service} ready in federation "


def start(prefix: str, subnet: str, service: str, rundir: Path) -> subprocess.Popen[bytes]:
    """Start one service in its namespace, its output to ``rundir/logs/<service>.log``."""
    log_path = rundir / "logs" / f"{service}.log"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with log_path.open("wb") as log:
        # Its own session: the service outlives `up` and no terminal signal reaches it.
        return subprocess.Popen(
            in_namespace(namespace(prefix, service), command(service, rundir, subnet)),
            cwd=ROOT,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def tail(path: Path, lines: int = 15) -> str:
    """The last lines of a log file, indented (for an error message)."""
    try:
        text = path.read_text(errors="replace").splitlines()[-lines:]
    except OSError:
        return "    (no log)"
    return "\n".join(f"    {line}" for line in text) or "    (empty log)"


def await_ready(procs: dict[str, subprocess.Popen[bytes]], rundir: Path, timeout: float) -> None:
    """Wait (at most ``timeout`` s) until every service printed its ready line."""
    waiting = set(procs)
    deadline = time.monotonic() + timeout
    while waiting:
        for service in sorted(waiting):
            log = rundir / "logs" / f"{service}.log"
            if ready_line(service) in log.read_text(errors="replace"):
                say(f"{service} is ready (pid {procs[service].pid})")
                waiting.discard(service)
            elif procs[service].poll() is not None:
                raise Failure(
                    f"{service} exited with {procs[service].returncode} before it was ready; "
                    f"{log}:\n{tail(log)}"
                )
        if waiting and time.monotonic() > deadline:
            logs = "\n".join(f"  {s}:\n{tail(rundir / 'logs' / f'{s}.log')}" for s in waiting)
            raise Failure(f"not ready within {timeout:g} s: {', '.join(sorted(waiting))}\n{logs}")
        if waiting:
            # The services write their logs on their own: nothing to await but the file.
            time.sleep(0.1)


def probe_router(prefix: str, subnet: str) -> None:
    """Connect from uav-a's namespace to the router's address: a Failure if it is not there."""
    target = (address(subnet, "router"), PORT)
    code = f"import socket; socket.create_connection({target!r}, timeout=5).close()"
    ns = namespace(prefix, "uav-a")
    proc = subprocess.run(
        ["ip", "netns", "exec", ns, sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    if proc.returncode != 0:
        reason = (proc.stderr.strip().splitlines() or ["?"])[-1]
        raise Failure(f"the router is not reachable at {target[0]}:{PORT} from {ns}: {reason}")
    say(f"the router accepts connections at {target[0]}:{PORT} from {ns}")


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[-1].split()[0] != "Z"


def processes_of(prefix: str, rundir: Path | None) -> set[int]:
    """Pids in the run's namespaces, plus any ``federation.cli`` process naming ``rundir``."""
    pids: set[int] = set()
    for ns in namespaces_of(prefix):
        pids.update(int(p) for p in ip("netns", "pids", ns, check=False).split())
    if rundir is not None:
        # A process whose namespace was deleted under it is found by its command line.
        marker = f"{rundir}/".encode()
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit() or int(entry.name) == os.getpid():
                continue
            try:
                cmdline = (entry / "cmdline").read_bytes()
            except OSError:
                continue
            if b"federation.cli" in cmdline and marker in cmdline:
                pids.add(int(entry.name))
    return {p for p in pids if pid_alive(p)}


def stop_processes(pids: Iterable[int], grace: float) -> None:
    """SIGTERM ``pids``; SIGKILL those still running after ``grace`` s; wait until gone."""
    pending = {p for p in pids if pid_alive(p)}
    for sig, bound in ((signal.SIGTERM, grace), (signal.SIGKILL, 5.0)):
        if not pending:
            return
        say(f"{sig.name} to {len(pending)} process(es): {' '.join(map(str, sorted(pending)))}")
        for pid in pending:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + bound
        while pending and time.monotonic() < deadline:
            for pid in list(pending):
                try:
                    os.waitpid(pid, os.WNOHANG)  # our own child (run): reap it
                except ChildProcessError:
                    pass
                if not pid_alive(pid):
                    pending.discard(pid)
            if pending:
                time.sleep(0.05)  # other processes' exits cannot be awaited: poll /proc
    if pending:
        raise Failure(f"processes survive SIGKILL: {' '.join(map(str, sorted(pending)))}")


# -- state --------------------------------------------------------------------------------------


def read_state(rundir: Path) -> dict[str, Any]:
    """The state ``up`` wrote into ``rundir``, or a Failure saying there is none."""
    path = rundir / STATE
    try:
        state = json.loads(path.read_text())
    except FileNotFoundError:
        raise Failure(f"{path}: no such file (no `up` into this directory?)") from None
    except (OSError, ValueError) as exc:
        raise Failure(f"{path}: unreadable: {exc}") from None
    if not isinstance(state, dict) or not isinstance(state.get("prefix"), str):
        raise Failure(f"{path}: not a state file of deploy/netns.py")
    return state


def resolve(args: argparse.Namespace) -> tuple[str, Path | None, dict[str, Any] | None]:
    """``(prefix, rundir, state)`` from --prefix and/or --dir."""
    rundir = None if args.dir is None else Path(args.dir).resolve()
    state = None
    if rundir is not None and (rundir / STATE).exists():
        state = read_state(rundir)
    prefix = args.prefix or (state or {}).get("prefix")
    if prefix is None:
        raise Failure("give --dir of an `up` (it has netns.json) or the run's --prefix", 2)
    return check_prefix(prefix), rundir, state


# -- commands -----------------------------------------------------------------------------------


def up(prefix: str, subnet: str, rundir: Path, timeout: float) -> dict[str, Any]:
    """Namespaces, links, configs and the five processes; the state written to ``rundir``."""
    check_prerequisites()
    if namespaces_of(prefix):
        raise Failure(f"prefix {prefix} is in use: `down --prefix {prefix}` first, or another")
    (rundir / "logs").mkdir(parents=True, exist_ok=True)
    state: dict[str, Any] = {
        "prefix": prefix,
        "subnet": subnet,
        "dir": str(rundir),
        "services": {
            s: {
                "namespace": namespace(prefix, s),
                "address": address(subnet, s),
                "log": str(rundir / "logs" / f"{s}.log"),
                "command": ["dyknow", *command(s, rundir, subnet)],
            }
            for s in SERVICES
        },
    }
    (rundir / STATE).write_text(json.dumps(state, indent=2))
    say(f"up {prefix}: {subnet}.0/24, files in {rundir}")
    try:
        make_network(prefix, subnet)
        write_configs(rundir, subnet)
        say("starting the router")
        procs = {"router": start(prefix, subnet, "router", rundir)}
        state["services"]["router"]["pid"] = procs["router"].pid
        await_ready(procs, rundir, timeout)
        probe_router(prefix, subnet)
        say(f"starting {', '.join(PLATFORMS)} (zenoh clients of the router)")
        for p in PLATFORMS:
            procs[p] = start(prefix, subnet, p, rundir)
            state["services"][p]["pid"] = procs[p].pid
        (rundir / STATE).write_text(json.dumps(state, indent=2))
        await_ready({p: procs[p] for p in PLATFORMS}, rundir, timeout)
    except BaseException:
        say("up failed: removing what it made")
        down(prefix, rundir, grace=2.0)
        raise
    (rundir / STATE).write_text(json.dumps(state, indent=2))
    for s in SERVICES:
        info = state["services"][s]
        say(f"{s:<9} {info['namespace']:<18} {info['address']:<15} pid {info['pid']}")
    say(f"all up; logs in {rundir / 'logs'}; stop with: {sys.argv[0]} down --dir {rundir}")
    return state


def dyknow_in(ns: str, args: Sequence[str], timeout: float) -> subprocess.CompletedProcess[str]:
    """Run one ``dyknow`` command in namespace ``ns`` (bounded); its completed process."""
    try:
        return subprocess.run(
            in_namespace(ns, args),
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
    except subprocess.TimeoutExpired:
        raise Failure(f"`dyknow {' '.join(args)}` in {ns} took more than {timeout:g} s") from None


def check(state: dict[str, Any], timeout: float) -> dict[str, Any]:
    """From the operator's namespace: the UAVs are alive, and uav-a answers a request."""
    check_prerequisites()
    prefix, rundir = state["prefix"], Path(state["dir"])
    ns, config = namespace(prefix, "operator"), str(rundir / "operator.toml")
    want = {p for p in PLATFORMS if p != "operator"}
    deadline = time.monotonic() + timeout
    seen: dict[str, Any] = {}
    while True:
        say(f"in {ns}: dyknow platforms --config {config} --json")
        left = max(1.0, deadline - time.monotonic())
        proc = dyknow_in(ns, ["platforms", "--config", config, "--json", "--wait", "3"], left + 5)
        if proc.returncode == 0:
            seen = json.loads(proc.stdout)
            if want <= set(seen):
                break
            say(f"operator sees {sorted(seen) or 'nobody'} so far")
        else:
            say(f"dyknow platforms exited {proc.returncode}: {proc.stderr.strip()}")
        if time.monotonic() > deadline:
            raise Failure(f"the operator did not see {sorted(want - set(seen))} in {timeout:g} s")
    say(f"operator sees {', '.join(sorted(seen))} alive, across namespaces through the router")
    say(f"in {ns}: dyknow labels --platform uav-a --config {config} --json")
    proc = dyknow_in(ns, ["labels", "--platform", "uav-a", "--config", config, "--json"], 30.0)
    if proc.returncode != 0:
        raise Failure(
            f"dyknow labels --platform uav-a exited {proc.returncode}: {proc.stderr.strip()}"
        )
    labels = json.loads(proc.stdout)
    say(f"uav-a answered the operator's request: {labels}")
    return {"platforms": seen, "labels": {"uav-a": labels}}


def status(prefix: str) -> int:
    """Print each service's namespace, address, pid and whether it runs; 0 if all run."""
    check_prerequisites()
    existing = set(namespaces_of(prefix))
    running = 0
    for s in SERVICES:
        ns = namespace(prefix, s)
        pids, addr = [], "-"
        if ns in existing:
            pids = ip("netns", "pids", ns, check=False).split()
            found = ip("-n", ns, "-4", "-o", "addr", "show", "dev", "eth0", check=False).split()
            addr = found[found.index("inet") + 1].split("/")[0] if "inet" in found else "-"
        alive = [int(p) for p in pids if pid_alive(int(p))]
        running += bool(alive)
        where = "namespace present" if ns in existing else "no namespace"
        what = f"running (pid {' '.join(map(str, alive))})" if alive else "not running"
        print(f"{s:<9} {ns:<18} {addr:<15} {where}, {what}", flush=True)
    switch = namespace(prefix, SWITCH)
    print(f"{'bridge':<9} {switch:<18} {'br0':<15} {'present' if switch in existing else 'absent'}")
    return 0 if running == len(SERVICES) else 1


def down(prefix: str, rundir: Path | None, grace: float) -> None:
    """Stop the run's processes (SIGTERM, then SIGKILL) and delete its namespaces; idempotent."""
    check_prerequisites()
    stop_processes(processes_of(prefix, rundir), grace)
    existing = namespaces_of(prefix)
    for ns in existing:
        ip("netns", "del", ns)  # its veth ends and the bridge go with it
    if existing:
        say(f"deleted {', '.join(existing)}")
    else:
        say(f"no namespace of {prefix} left")


# -- command line -------------------------------------------------------------------------------


def parser() -> argparse.ArgumentParser:
    """The command line: up, check, status, down, run."""
    ap = argparse.ArgumentParser(
        prog="deploy/netns.py",
        description="The zenoh federation topology in Linux network namespaces (needs root).",
    )
    sub = ap.add_subparsers(dest="command", required=True)
    for name, text in (
        ("up", "create namespaces, keys and configs; start router and platforms"),
        ("check", "from the operator: the UAVs are alive and answer"),
        ("status", "show the run's namespaces and processes"),
        ("down", "stop the processes and delete the namespaces (idempotent)"),
        ("run", "up, check, down"),
    ):
        cmd = sub.add_parser(name, help=text, description=text)
        cmd.add_argument("--dir", help="the run directory (keys, configs, logs, netns.json)")
        cmd.add_argument("--prefix", help="namespace name prefix (default: dk<pid> for up)")
        if name in ("up", "run"):
            cmd.add_argument("--subnet", default="10.231.0", help="a private /24: 3 octets")
        if name in ("up", "run", "check"):
            cmd.add_argument("--timeout", type=float, default=30.0, help="bound per step, s")
        if name in ("check", "run"):
            cmd.add_argument("--json", action="store_true", help="end with a JSON line")
        if name in ("down", "run"):
            cmd.add_argument("--grace", type=float, default=10.0, help="SIGTERM to SIGKILL, s")
    return ap


def _interrupted(signum: int, frame: object) -> None:
    """Turn SIGTERM into KeyboardInterrupt, so that `up` and `run` remove what they made."""
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; the exit code (0 ok, 1 a step failed, 2 usage or no root/ip)."""
    args = parser().parse_args(argv)
    # SIGTERM (a supervisor, a test's timeout) cleans up as Ctrl-C does.
    signal.signal(signal.SIGTERM, _interrupted)
    try:
        if args.command in ("up", "run"):
            if args.dir is None:
                raise Failure(f"{args.command}: --dir is required", 2)
            subnet = check_subnet(args.subnet)
            given = check_prefix(args.prefix) if args.prefix else None
            check_prerequisites()
            prefix = given or free_prefix()
            rundir = Path(args.dir).resolve()
            state = up(prefix, subnet, rundir, args.timeout)
            if args.command == "up":
                return 0
            try:
                result = check(state, args.timeout)
            finally:
                down(prefix, rundir, args.grace)
            if args.json:
                print(json.dumps(result, sort_keys=True), flush=True)
            return 0
        prefix, given_dir, maybe_state = resolve(args)
        if args.command == "status":
            return status(prefix)
        if args.command == "down":
            down(prefix, given_dir, args.grace)
            return 0
        if maybe_state is None:
            raise Failure("check: give the --dir of a running `up`", 2)
        result = check(maybe_state, args.timeout)
        if args.json:
            print(json.dumps(result, sort_keys=True), flush=True)
        return 0
    except Failure as exc:
        print(f"netns: {exc}", file=sys.stderr, flush=True)
        return exc.code
    except OSError as exc:  # the run directory cannot be made or written, a file unreadable
        print(f"netns: {exc}", file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        print("netns: interrupted", file=sys.stderr, flush=True)
        return 130


if __name__ == "__main__":
    sys.exit(main())
