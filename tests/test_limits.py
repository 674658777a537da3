"""What a member can still make a platform accept, and limits a config gives as ``inf``.

A member that said, signed, that it left is not served until its signed directory
snapshot lists it again. A config's numeric limits are checked when the file is read
(a limit of ``inf`` or ``nan`` is TOML, and none of ours means anything with it),
naming file, table and key.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest
from test_member_authz import WAIT, audited, world

from agents import Refused
from federation import PlatformConfig, PlatformConfigError

_BASE = 'name = "uav-a"\nfederation = "f"\nkey = "k"\ntrust = "t"\nvocabulary = {}\nmapping = {}\n'


@pytest.mark.parametrize(
    ("table", "key", "value"),
    [
        ("rate_limit", "rate", "inf"),
        ("rate_limit", "total_burst", "nan"),
        ("kx_limit", "per_peer", "inf"),
        ("kx_limit", "report_interval", "inf"),
        ("df_event_limit", "total", "+inf"),
        ("df_event_limit", "per_platform", "-1.0"),
        ("console", "idle_timeout", "nan"),
        ("transport", "serve_timeout", "inf"),
    ],
)
def test_a_limit_of_inf_nan_or_below_zero_is_refused_when_the_file_is_read(
    tmp_path: Path, table: str, key: str, value: str
) -> None:
    path = tmp_path / "uav-a.toml"
    path.write_text(f"{_BASE}[{table}]\n{key} = {value}\n")
    with pytest.raises(PlatformConfigError, match=rf"^{path}: {table}\.{key}: ") as caught:
        PlatformConfig.load(path)
    assert value.lstrip("+-") in ("inf", "nan") or "greater than" in caught.value.message
    path.write_text(f"{_BASE}export_lease = inf\n")
    with pytest.raises(PlatformConfigError, match=rf"^{path}: export_lease: .*finite"):
        PlatformConfig.load(path)


def test_the_node_refuses_an_inf_limit_naming_file_table_and_key(tmp_path: Path) -> None:
    """``dyknow node`` (a process): exit 2 and one line naming where, not a start-up error."""
    path = tmp_path / "uav-a.toml"
    path.write_text(f"{_BASE}[rate_limit]\nrate = inf\n")
    run = subprocess.run(
        [sys.executable, "-m", "federation.cli", "node", "--config", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 2, run.stderr
    assert f"{path}: rate_limit.rate: Input should be a finite number" in run.stderr
    assert "Traceback" not in run.stderr


async def test_a_member_that_said_it_left_is_not_served_until_listed_again(
    tmp_path: Path,
) -> None:
    """uav-m says, signed, that it leaves, and keeps asking uav-a (a spawned platform)."""
    async with asyncio.timeout(150), world(tmp_path, ["uav-a"]) as w:
        m = w.here["uav-m"]
        fed = m.federation_agent
        assert (await fed.create_stream("uav-a", ["car0-state"], timeout=WAIT)).startswith("x-")
        assert m.agents.df is not None
        await m.agents.df.announce_leave()
        # uav-a took it for gone (its exports to it stopped); before, it went on serving it
        await w.until_stats("uav-a", lambda s: s["exports"] == [], "uav-m taken for gone")
        with pytest.raises(Refused, match=r"refused: left: 'uav-m' said, signed, that it left"):
            await fed.create_stream("uav-a", ["car1-state"], timeout=WAIT)
        s = await w.stats("uav-a")
        assert s["platform"]["from_left"] == 1 and s["exports"] == []
        recs = audited(s, verdict="refused", sender="federation@uav-m", reason="left: 'uav-m'")
        assert len(recs) == 1, recs
        # it announces itself again (as a new process would): its presence comes back and
        # its directory answers, signed; listed again, it is served again
        agents = m.agents
        agents.df._left = False
        assert agents._token is not None
        await agents._token.aclose()
        await asyncio.sleep(0.5)
        agents._token = await agents.transport.declare_token(agents.key("alive"))
        async with asyncio.timeout(WAIT):
            while True:
                try:
                    await fed.create_stream("uav-a", ["car1-state"], timeout=WAIT)
                    break
                except Refused as exc:
                    assert "left: 'uav-m'" in str(exc)
                    await asyncio.sleep(0.2)
