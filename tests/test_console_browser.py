"""The operator console as a person sees it: headless Chromium (Playwright) against a federation.

`running_federation` is the one fixture that knows what runs: the real traffic demo
(`run_traffic_demo`, what `dyknow demo traffic` runs), three UAV processes over zenoh and
the operator with its console in the test process, the world at 4x (slower on a loaded
machine). It yields the console's URL with its token (what the demo prints), the UAVs'
names, the world's speed and a way to kill one (SIGKILL).

Chromium resolves ``evil.example`` to 127.0.0.1 (``--host-resolver-rules``): a page of
that site reaching the console is what a DNS-rebinding attack looks like to it.

Chromium is Debian's (``/usr/bin/chromium``; `make test` installs it), never a
Playwright download. Without it the test fails in CI and is skipped, saying why, elsewhere.

`test_the_console_reads_clearly` looks at the page as laid out at 1280 and 1920 px: map
labels and area titles that never overlap, a legend entry for every kind of mark drawn,
a map at least 60% of the window high, every violation (speeding too) listed with its
time, car and platform, as many as the demo's report counts, and a label search that
finds the tracked cars. Its screenshots go to ``artifacts/console/`` (git-ignored; CI
keeps the folder), ``DYKNOW_ARTIFACTS`` elsewhere; with ``DYKNOW_DOC_SCREENSHOT=1`` the
1280 px one also becomes docs/img/console.png.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import shutil
import signal
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from _load import slowdown

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
SPEED = 4.0  # simulated seconds per second, on a machine of its own
ROOT = Path(__file__).resolve().parent.parent
ARTIFACTS = Path(os.environ.get("DYKNOW_ARTIFACTS") or ROOT / "artifacts") / "console"
DOC_SCREENSHOT = ROOT / "docs" / "img" / "console.png"
SIZES = [(1280, 800), (1920, 1080)]  # a laptop's window, a desktop's


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
    said: list[str]  # what the demo printed so far (its report at the end)
    speed: float  # the world's, simulated seconds per second: what rates count on


@contextlib.asynccontextmanager
async def _real_demo(tmp_path: Path, speed: float) -> AsyncIterator[RunningFederation]:
    """`dyknow demo traffic` (3 UAV processes, the operator here), kept up while we look."""
    options = DemoOptions(
        uavs=3, duration=60.0, seed=1, speed=speed, port=0, hold=600.0, run_dir=str(tmp_path)
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

        yield RunningFederation(info.console_url, sorted(info.pids), kill, said, speed)
    finally:
        demo.cancel()  # its children are stopped on the way out
        with contextlib.suppress(asyncio.CancelledError):
            await demo


@pytest.fixture
async def running_federation(tmp_path: Path) -> AsyncIterator[RunningFederation]:
    """The federation the console runs against: the real traffic demo.

    Its world at `SPEED`; a process that gets a quarter of a CPU or less would fall behind
    it (as in the demo's own test): the world then runs slower, 1x at least.
    """
    _require_chromium()
    async with _real_demo(tmp_path, SPEED / min(SPEED, slowdown())) as running:
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


async def _another_port_gets_nothing(browser: Any, token: str) -> None:
    """A server on another port of the console's host gets no credential from the browser.

    Browsers keep cookies per host, not per port: a cookie of the console's would reach
    any local server the browser visits (found in Chromium). The token is no cookie.
    """
    from aiohttp import web

    seen: list[dict[str, str]] = []

    async def record(request: web.Request) -> web.Response:
        seen.append(dict(request.headers))
        return web.Response(text="<title>another server</title>", content_type="text/html")

    app = web.Application()
    app.router.add_get("/{tail:.*}", record)
    runner = web.AppRunner(app)
    await runner.setup()
    try:
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        port = runner.addresses[0][1]
        page = await browser.new_page()
        try:
            await page.goto(f"http://127.0.0.1:{port}/api/state")
        finally:
            await page.close()
    finally:
        await runner.cleanup()
    assert seen, "the other server was not reached"
    for headers in seen:
        assert "Cookie" not in headers and "Authorization" not in headers, headers
        assert token not in repr(headers), headers


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
            # without the token: the page (the same for all), saying it is refused, and
            # nothing of the state; its own origin without a token reads nothing either
            await page.goto(base)
            await expect(page.locator("#connection")).to_have_attribute("data-state", "refused")
            await expect(page.locator("#platforms li")).to_have_count(0)
            status = await page.evaluate("() => fetch('/api/state').then((r) => r.status)")
            assert status == 401, status
            await page.goto(url)
            await expect(page).to_have_title("DyKnow Federation — operator console")
            await expect(page.locator("#connection")).to_have_text("live")
            assert "token" not in page.url  # kept by the page, out of the address bar
            assert await browser.cookies() == []  # no cookie: it would reach every port
            await _another_port_gets_nothing(browser, token)
            await page.reload()  # the token stays with the tab (sessionStorage), not the URL
            await expect(page.locator("#connection")).to_have_text("live")
            assert "token" not in page.url
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
                re.compile("overtake|turn"), timeout=40_000 * int(2 / running_federation.speed + 1)
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
            row_css = f'#platforms li[data-platform="{a}"] tr[data-stream="tracked-cars"]'
            row = page.locator(row_css)
            await row.locator("input").fill("2")
            await row.locator("button").click()
            await expect(row.locator(".policy")).to_have_text("2 s")
            # one sample every 2 simulated seconds: about two a second at 4x (it was eight)
            rate = running_federation.speed / 2
            await page.wait_for_function(
                """([row, low, high]) => {
                  const text = document.querySelector(row + ' .rate')?.textContent || '';
                  const m = /^(\\d+\\.\\d)\\/s$/.exec(text);
                  return m !== null && +m[1] >= low && +m[1] <= high; }""",
                arg=[row_css, round(0.6 * rate, 1), round(1.4 * rate, 1)],
                timeout=15_000,
            )

            # an observation: click on the map, type, add; it is listed (and drawn)
            await page.locator("#map").scroll_into_view_if_needed()
            box = await page.locator("#map").bounding_box()
            assert box is not None
            await page.mouse.click(box["x"] + box["width"] * 0.3, box["y"] + box["height"] * 0.5)
            assert await page.input_value("#obs-x") != ""
            await page.fill("#obs-text", "accident at the first crossing")
            await page.click("#observation-form button[type=submit]")
            await expect(page.locator("#observations li")).to_contain_text(
                "accident at the first crossing"
            )
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            await page.screenshot(path=str(ARTIFACTS / "console-1500-observation.png"))

            # a UAV killed: shown as gone, its cars off the list
            await running_federation.kill(b)
            await expect(
                page.locator(f'#platforms li[data-platform="{b}"][data-state="gone"]')
            ).to_be_visible()
            await expect(page.locator(f'#cars [data-platform="{b}"]')).to_have_count(0)
            await expect(page.locator(f'#platforms li[data-platform="{a}"]')).to_have_attribute(
                "data-state", "alive"
            )
            await page.evaluate("() => window.scrollTo(0, 0)")
            await page.screenshot(path=str(ARTIFACTS / "console-1500-gone.png"))
        finally:
            await browser.close()


# -- readable: what a person sees at a laptop's and a desktop's width --------------------------

# every visible map label's box (canvas pixels are page pixels here), area titles included
_LABEL_BOXES = """() => [...document.querySelectorAll('#map-labels .map-label')]
  .filter((n) => n.offsetParent !== null)
  .map((n) => { const r = n.getBoundingClientRect();
    return {key: n.dataset.key, kind: n.dataset.kind, text: n.textContent,
            x: r.left, y: r.top, w: r.width, h: r.height,
            clipped: n.scrollWidth > n.clientWidth + 1}; })"""


def _overlapping(boxes: list[dict[str, Any]]) -> list[tuple[str, str]]:
    """The pairs of boxes that share more than a hairline."""
    pairs = []
    for i, a in enumerate(boxes):
        for b in boxes[i + 1 :]:
            dx = min(a["x"] + a["w"], b["x"] + b["w"]) - max(a["x"], b["x"])
            dy = min(a["y"] + a["h"], b["y"] + b["h"]) - max(a["y"], b["y"])
            if dx > 0.5 and dy > 0.5:
                pairs.append((a["text"], b["text"]))
    return pairs


async def _check_layout(page: Any, width: int, uavs: list[str], *, cars: bool = True) -> None:
    """The map's size, its labels, area titles and legend, at the page's width.

    ``cars``: cars are on the map (the traffic has not ended).
    """
    from playwright.async_api import expect

    # the map uses the window: at least 60% of its height, its whole width but the margins
    size = await page.evaluate(
        """() => { const r = document.querySelector('#map').getBoundingClientRect();
          return {w: r.width, h: r.height, vw: innerWidth, vh: innerHeight}; }"""
    )
    assert size["h"] >= 0.6 * size["vh"] and size["w"] >= 0.9 * size["vw"], (width, size)

    boxes = await page.evaluate(_LABEL_BOXES)
    assert not _overlapping(boxes), (width, _overlapping(boxes))
    # one title per monitored area, each whole (not cut) and clear of the others
    titles = [b for b in boxes if b["kind"] == "area-title"]
    assert len(titles) == len(uavs) and not [t for t in titles if t["clipped"]], (width, titles)
    assert all(any(u in t["text"] for t in titles) for u in uavs), (width, titles)
    kinds = {b["kind"] for b in boxes}
    assert {"uav", "car"} - ({"car"} if not cars else set()) <= kinds, (width, boxes)

    # every kind of mark the map drew has its entry in the legend
    drawn = (await page.get_attribute("#map", "data-marks") or "").split()
    expected = {"uav", "uav-area", "violation", "road", "crossing", "parking"}
    assert expected | ({"car"} if cars else set()) <= set(drawn), (width, drawn)
    for kind in drawn:
        await expect(page.locator(f'#legend li[data-mark="{kind}"]')).to_be_visible()


async def _check_violations(page: Any) -> None:
    """Speeding listed with the others, each row with its time, car and platform."""
    from playwright.async_api import expect

    speeding = page.locator('#violations li[data-kind="speeding"]').first
    await expect(speeding).to_be_visible()
    await expect(speeding.locator(".time")).to_have_text(re.compile(r"^t \d+\.\d s$"))
    await expect(speeding.locator(".car")).to_have_text(re.compile(r"uav_\w+_car\d+"))
    await expect(speeding.locator(".platform")).to_have_text(re.compile(r"^uav-\w"))
    rows = page.locator("#violations li")
    for i in range(await rows.count()):
        for part in (".time", ".kind", ".car", ".platform"):
            assert (await rows.nth(i).locator(part).inner_text()).strip() not in ("", "–")


async def _check_map_moves(page: Any) -> None:
    """Zoom (buttons, wheel), pan (drag), the whole map again; a hovered mark says what it is."""
    from playwright.async_api import expect

    def view() -> Any:
        return page.evaluate("() => window.dyknowMap.view()")

    box = await page.locator("#map").bounding_box()
    assert box is not None
    before = await view()
    await page.click("#zoom-in")
    await expect(page.locator("#map")).to_have_attribute("data-zoom", "1.50")
    await page.mouse.move(box["x"] + box["width"] * 0.3, box["y"] + box["height"] * 0.5)
    await page.mouse.wheel(0, -300)
    await page.wait_for_function("() => window.dyknowMap.view().zoom > 1.6")
    zoomed = await view()
    await page.mouse.down()
    await page.mouse.move(box["x"] + box["width"] * 0.5, box["y"] + box["height"] * 0.6, steps=5)
    await page.mouse.up()
    panned = await view()
    assert panned["cx"] < zoomed["cx"] and panned["cy"] > zoomed["cy"], (zoomed, panned)
    boxes = await page.evaluate(_LABEL_BOXES)
    assert not _overlapping(boxes), _overlapping(boxes)
    await page.screenshot(path=str(ARTIFACTS / "console-1920-zoomed.png"))
    # a drag is no click: no point was picked for an observation
    assert await page.input_value("#obs-x") == ""
    await page.click("#zoom-fit")
    await expect(page.locator("#map")).to_have_attribute("data-zoom", "1.00")
    assert await view() == before

    # hovering a car says which it is and who tracks it (its label may have had no room):
    # the car farthest from any other mark, so that it is the one under the pointer; cars
    # move while the pointer does (more so on a busy machine), so it is found and hovered
    # again until the tip names it, a bounded number of times
    tip = page.locator("#map-tip")
    said = ""
    for _ in range(20):
        car = await page.evaluate(
            """() => { const ms = window.dyknowMap.marks(); let best = null, room = -1;
              for (const m of ms.filter((m) => m.kind === 'car')) {
                const d = Math.min(...ms.filter((o) => o !== m && o.kind !== 'crossing')
                  .map((o) => Math.hypot(o.x - m.x, o.y - m.y)), 1e9);
                if (d > room) { room = d; best = m; } }
              return best; }"""
        )
        assert car is not None
        await page.mouse.move(box["x"] + car["x"], box["y"] + car["y"])
        with contextlib.suppress(AssertionError):
            await expect(tip).to_contain_text("tracked by", timeout=1000)
            break
        said = await tip.inner_text()
    else:
        raise AssertionError(f"hovering a car never said who tracks it; the tip said {said!r}")


async def _check_search(page: Any) -> None:
    """The label search's default formula finds the tracked cars' states."""
    from playwright.async_api import expect

    assert await page.input_value("#search-formula") == "(all ?x (Car ?x))"
    await page.click("#search-form button[type=submit]")
    found = page.locator('#query-result tr[data-platform^="uav-"]:not([data-labels="0"])')
    await expect(found.first).to_contain_text(re.compile(r"uav_\w+_car\d+-state"))
    # nothing the operator provides satisfies it: its row says so, not just "–"
    await expect(page.locator('#query-result tr[data-platform="operator"]')).to_contain_text(
        "nothing this platform provides"
    )
    await page.fill("#search-formula", "(all ?x (Car ?x)")
    await page.click("#search-form button[type=submit]")
    await expect(page.locator('#query-result [data-testid="error"]')).to_contain_text("formula")
    await page.fill("#search-formula", "(all ?x (and (Car ?x) (Colour ?x chartreuse)))")
    await page.click("#search-form button[type=submit]")
    await expect(page.locator("#query-result .caption")).to_contain_text("no platform provides")
    await page.fill("#search-formula", "(all ?x (Car ?x))")


@pytest.mark.timeout(240)
async def test_the_console_reads_clearly(
    running_federation: RunningFederation, tmp_path: Path
) -> None:
    from playwright.async_api import async_playwright, expect

    fed = running_federation
    expect.set_options(timeout=WAIT)
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    async with async_playwright() as pw:
        browser = await pw.chromium.launch(
            executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True
        )
        try:
            pages = {}
            for width, height in SIZES:
                context = await browser.new_context(viewport={"width": width, "height": height})
                page = pages[width] = await context.new_page()
                await page.goto(fed.url)

            # mid-run: cars on the map, speeding and a recognized event listed (t≈25 s)
            first = pages[1280]
            speeding = first.locator('#violations li[data-kind="speeding"]')
            await expect(speeding).not_to_have_count(0, timeout=60_000)
            recognized = first.locator('#violations li:not([data-kind="speeding"])')
            await expect(recognized).not_to_have_count(0, timeout=60_000)
            for (width, _), page in zip(SIZES, pages.values(), strict=True):
                await expect(page.locator("#cars [data-car]").first).to_be_visible()
                await _check_layout(page, width, fed.uavs)
                await _check_violations(page)
                shot = ARTIFACTS / f"console-{width}.png"
                await page.evaluate("() => window.scrollTo(0, 0)")
                await page.screenshot(path=str(shot))
                print(f"screenshot: {shot}")
            if os.environ.get("DYKNOW_DOC_SCREENSHOT"):
                DOC_SCREENSHOT.parent.mkdir(exist_ok=True)
                shutil.copyfile(ARTIFACTS / "console-1280.png", DOC_SCREENSHOT)
            await _check_search(first)
            await _check_map_moves(pages[1920])

            # the demo's report counts what the console lists (speeding included)
            async with asyncio.timeout(120):
                # the demo prints into a plain list: looked at twice a second
                while not (done := [x for x in fed.said if x.startswith("violations reported:")]):  # noqa: ASYNC110
                    await asyncio.sleep(0.5)
            reported = int(done[0].split()[2])
            assert reported >= 2, fed.said  # the speeding car and a recognized event at least
            for page in pages.values():
                await expect(page.locator("#violation-count")).to_have_text(str(reported))
                await expect(page.locator("#violations li")).to_have_count(reported)
            for (width, _), page in zip(SIZES, pages.values(), strict=True):
                await _check_layout(page, width, fed.uavs, cars=False)
                await page.evaluate("() => window.scrollTo(0, 0)")
                await page.screenshot(path=str(ARTIFACTS / f"console-{width}-end.png"))
                await page.screenshot(
                    path=str(ARTIFACTS / f"console-{width}-end-page.png"), full_page=True
                )
        finally:
            await browser.close()
