"""The operator console as a person sees it: headless Chromium (Playwright) against a federation.

`running_federation` is the one fixture that knows what runs: the real traffic demo
(`run_traffic_demo`, what `dyknow demo traffic` runs), three UAV processes over zenoh and
the operator with its console in the test process. It yields the console's URL with its
token (what the demo prints), the UAVs' names and a way to kill one (SIGKILL).

Chromium resolves ``evil.example`` to 127.0.0.1 (``--host-resolver-rules``): a page of
that site reaching the console is what a DNS-rebinding attack looks like to it.

Chromium is Debian's (``/usr/bin/chromium``; `make test` installs it), never a
Playwright download. Without it the test fails in CI and is skipped, saying why, elsewhere.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from federation.demo._run import DemoOptions, DemoStarted, run_traffic_demo

CHROMIUM = "/usr/bin/chromium"
EVIL = "evil.example"  # a name the attacker rebinds to the operator's loopback address
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    f"--host-resolver-rules=MAP {EVIL} 127.0.0.1",
]
WAIT = 15_000  # ms: the bound on one thing to appear on the page
SPEED = 2.0  # simulated seconds per second: the policy check below counts on it


def _require_chromium() -> None:
    why = None
    try:
        import playwright.async_api  # noqa: F401
    except ImportError:
        why = "the Python package playwright is not installed (pip install -e '.[dev]')"
    if why is None and not os.access(CHROMIUM, os.X_OK):
        why = f"{CHROMIUM} is missing: `make test` installs Debian's chromium package"
    if why is not None:
        if os.environ.get("CI"):
            pytest.fail(f"the console's browser test needs Chromium: {why}", pytrace=False)
        pytest.skip(f"the console's browser test needs Chromium: {why}")


# -- the fake UAVs (spawned processes) -------------------------------------------------------


@dataclass
class RunningFederation:
    """What the browser test drives: the console's URL (with its token), the UAVs, a kill."""

    url: str
    uavs: list[str]
    kill: Callable[[str], Awaitable[None]]


@contextlib.asynccontextmanager
async def _real_demo(tmp_path: Path) -> AsyncIterator[RunningFederation]:
    """`dyknow demo traffic` (3 UAV processes, the operator here), kept up while we look."""
    options = DemoOptions(
        uavs=3, duration=60.0, seed=1, speed=SPEED, port=0, hold=600.0, run_dir=str(tmp_path)
    )
    started: asyncio.Future[DemoStarted] = asyncio.get_running_loop().create_future()
    said: list[str] = []
    demo = asyncio.create_task(run_traffic_demo(options, said.append, started=started))
    try:
        async with asyncio.timeout(60):
            await asyncio.wait({demo, started}, return_when=asyncio.FIRST_COMPLETED)
        if demo.done():
            demo.result()  # the demo failed before it started: say why
        info = started.result()
        assert info.console_url is not None
        # what `dyknow demo traffic` prints: the URL to open, with the token
        assert re.fullmatch(r"http://127\.0\.0\.1:\d+/\?token=[\w-]{32}", info.console_url)
        assert f"operator console: {info.console_url}" in said, said

        async def kill(name: str) -> None:
            os.kill(info.pids[name], signal.SIGKILL)

        yield RunningFederation(info.console_url, sorted(info.pids), kill)
    finally:
        demo.cancel()  # its children are stopped on the way out
        with contextlib.suppress(asyncio.CancelledError):
            await demo


@pytest.fixture
async def running_federation(tmp_path: Path) -> AsyncIterator[RunningFederation]:
    """The federation the console runs against: the real traffic demo."""
    _require_chromium()
    async with _real_demo(tmp_path) as running:
        yield running


# -- the test --------------------------------------------------------------------------------


async def _rebinding_page_is_refused(browser: Any, base: str, token: str) -> None:
    """A page of evil.example, its name now 127.0.0.1, reads nothing and changes nothing."""
    port = base.rstrip("/").rsplit(":", 1)[1]
    evil = f"http://{EVIL}:{port}"
    page = await browser.new_page()
    try:
        # the page of evil.example:<port> (now served from 127.0.0.1: the console refuses
        # it, but the browser keeps the document, whose origin is evil.example's)
        first = await page.goto(f"{evil}/")
        assert first is not None and first.status == 403
        got = await page.evaluate(
            """async () => {
              const state = await fetch('/api/state');
              const policy = await fetch('/api/policy', {method: 'POST',
                headers: {'Content-Type': 'application/json'},
                body: JSON.stringify({platform: 'uav-a', label: 'tracked-cars',
                                      sample_period: 60})});
              return [state.status, await state.text(), policy.status];
            }"""
        )
        assert got[0] == 403 and "Host" in got[1] and "platforms" not in got[1], got
        assert got[2] == 403, got
    finally:
        await page.close()
    bearer = {"Authorization": f"Bearer {token}"}
    async with aiohttp.ClientSession(headers=bearer) as http, http.get(base + "api/stats") as r:
        stats = await r.json()
    assert stats["refused"]["host"] >= 3 and stats["refused"]["no-token"] >= 1, stats


@pytest.mark.timeout(120)
async def test_what_the_operator_sees(
    running_federation: RunningFederation, tmp_path: Path
) -> None:
    from playwright.async_api import async_playwright, expect

    url, (a, b) = running_federation.url, running_federation.uavs[:2]
    expect.set_options(timeout=WAIT)
    async with async_playwright() as pw:
        browser = await pw.chromium.launch_persistent_context(
            str(tmp_path / "chromium-profile"),
            executable_path=CHROMIUM,
            args=CHROMIUM_ARGS,
            headless=True,
            viewport={"width": 1500, "height": 1000},
        )
        try:
            page = browser.pages[0] if browser.pages else await browser.new_page()
            base, token = url.split("?token=")
            refused = await page.goto(base)  # without the token: refused, nothing shown
            assert refused is not None and refused.status == 401
            await page.goto(url)
            await expect(page).to_have_title("DyKnow Federation — operator console")
            assert "token" not in page.url  # traded for a cookie, out of the address bar
            await _rebinding_page_is_refused(browser, base, token)

            # platforms listed, alive, their streams active
            for name in (a, b):
                li = page.locator(f'#platforms li[data-platform="{name}"][data-state="alive"]')
                await expect(li).to_be_visible()
                await expect(li.locator('tr[data-stream="tracked-cars"] .st')).to_have_text(
                    "active"
                )
            await expect(page.locator("#connection")).to_have_text("live")

            # cars listed (and drawn: the map is not blank)
            await expect(page.locator("#cars [data-car]").first).to_be_visible()
            drawn = await page.evaluate(
                """() => { const c = document.querySelector('#map');
                  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                  let ink = 0; for (let i = 0; i < d.length; i += 4 * 7) if (d[i + 3]) ink++;
                  return ink; }"""
            )
            assert drawn > 1000, drawn

            # a violation appears in the list (the first scripted one comes at t≈21 s)
            first = page.locator("#violations li").first
            await expect(first).to_contain_text(
                re.compile("overtake|turn"), timeout=40_000 * int(2 / SPEED + 1)
            )

            # a query returns a table
            await page.select_option("#query-platform", a)
            await page.fill("#query-label", "heli-position")
            await page.select_option("#query-kind", "between")
            await page.fill("#query-from", "-2")
            await page.fill("#query-to", "0")
            await page.click("#query-form button[type=submit]")
            rows = page.locator('#query-result table[data-testid="result-table"] tbody tr')
            await expect(rows.first).to_be_visible()
            assert await rows.count() >= 3  # 2 Hz over 2 s of the UAV's (simulated) time
            table = page.locator('#query-result table[data-testid="result-table"]')
            await expect(table.locator("thead")).to_contain_text("z")  # a column per key
            await expect(rows.first).to_contain_text("60")  # the UAVs fly at 60 m
            # a label search answers for every platform
            await page.click("#search-form button[type=submit]")
            for name in (a, b, "operator"):
                answer = page.locator(f'#query-result tr[data-platform="{name}"]')
                await expect(answer).to_be_visible()
            # a bad query says what is wrong
            await page.fill("#query-label", "weather")
            await page.click("#query-form button[type=submit]")
            await expect(page.locator('#query-result [data-testid="error"]')).to_contain_text(
                "label"
            )

            # a policy change is reflected
            row = page.locator(f'#platforms li[data-platform="{a}"] tr[data-stream="tracked-cars"]')
            await row.locator("input").fill("2")
            await row.locator("button").click()
            await expect(row.locator(".policy")).to_have_text("2 s")
            # one sample every 2 simulated seconds: about one a second at 2x (it was four)
            await expect(row.locator(".rate")).to_have_text(
                re.compile(r"^(0\.[6-9]|1\.[0-4])/s$"), timeout=15_000
            )

            # an observation: click on the map, type, add; it is listed (and drawn)
            box = await page.locator("#map").bounding_box()
            assert box is not None
            await page.mouse.click(box["x"] + box["width"] * 0.3, box["y"] + box["height"] * 0.5)
            assert await page.input_value("#obs-x") != ""
            await page.fill("#obs-text", "accident at the first crossing")
            await page.click("#observation-form button[type=submit]")
            await expect(page.locator("#observations li")).to_contain_text(
                "accident at the first crossing"
            )
            await page.screenshot(path=str(tmp_path / "console.png"))

            # a UAV killed: shown as gone, its cars off the list
            await running_federation.kill(b)
            await expect(
                page.locator(f'#platforms li[data-platform="{b}"][data-state="gone"]')
            ).to_be_visible()
            await expect(page.locator(f'#cars [data-platform="{b}"]')).to_have_count(0)
            await expect(page.locator(f'#platforms li[data-platform="{a}"]')).to_have_attribute(
                "data-state", "alive"
            )
            await page.screenshot(path=str(tmp_path / "console-gone.png"))
        finally:
            await browser.close()
