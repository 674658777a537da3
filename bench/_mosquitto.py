"""A mosquitto broker of the benchmark's own on a free loopback port (as the tests start it)."""

from __future__ import annotations

import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from agents.transports import free_tcp_port


class MosquittoMissing(RuntimeError):
    """mosquitto is not installed: the MQTT figures cannot be measured."""


def executable() -> str:
    """The mosquitto binary; MosquittoMissing (saying how to install it) when there is none."""
    found = shutil.which("mosquitto")
    if found:
        return found
    if Path("/usr/sbin/mosquitto").is_file():  # Debian's place, not on every user's PATH
        return "/usr/sbin/mosquitto"
    raise MosquittoMissing(
        "mosquitto is not installed, and the MQTT round trip needs a real broker: "
        "run `make mosquitto` (installs it from Debian's packages) or "
        "`apt-get install -y mosquitto`"
    )


@contextmanager
def mosquitto(start_timeout: float = 10.0) -> Iterator[tuple[str, int]]:
    """Run a broker on 127.0.0.1:<free port> for the block: yields (host, port); always killed."""
    exe = executable()
    host, port = "127.0.0.1", free_tcp_port()
    with tempfile.TemporaryDirectory(prefix="bench-mosquitto-") as tmp:
        workdir = Path(tmp)
        conf = workdir / "mosquitto.conf"
        conf.write_text(
            f"listener {port} {host}\n"
            "allow_anonymous true\n"
            "persistence false\n"
            "set_tcp_nodelay true\n"
            "log_dest stdout\n"
        )
        log_path = workdir / "mosquitto.log"
        with log_path.open("wb") as log:
            proc = subprocess.Popen([exe, "-c", str(conf)], stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + start_timeout
            while True:
                if proc.poll() is not None:
                    raise RuntimeError(
                        f"mosquitto exited with {proc.returncode} at start:\n{log_path.read_text()}"
                    )
                try:
                    socket.create_connection((host, port), timeout=0.2).close()
                    break
                except OSError:
                    if time.monotonic() > deadline:
                        raise RuntimeError(
                            f"mosquitto did not accept connections on {host}:{port} within "
                            f"{start_timeout:g} s:\n{log_path.read_text()}"
                        ) from None
                    time.sleep(0.02)
            yield host, port
        finally:
            proc.kill()
            proc.wait(timeout=10)
