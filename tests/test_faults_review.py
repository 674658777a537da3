"""Regressions found by reviewing the fault handling (leases, durable streams, loss counts).

Each test failed before its fix: a durable stream could not be cancelled once created
again; a receiver whose export's lease expired was never told; an idle stream created
again after its sender came back lost its lease; a new export inherited the losses of
the old one; a lease shorter than the receivers' report interval ended live exports.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Any

import pytest

from federation import MembershipEvent, PlatformConfig, PlatformConfigError
from tests.test_federation_service import next_event, world
from tests.test_proxies import LOCAL, SEM, Net, agreed, until


async def test_a_durable_stream_created_again_is_cancelled_by_its_first_id() -> None:
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        first = await b.fed.create_stream("uav-a", ["car5-state"], durable=True)
        async with b.fed.membership() as seen:
            await a.fed.leave()
            assert await next_event(seen, MembershipEvent("left", "uav-a"))
            await a.fed._end(a.fed.exports[first])  # as after a restart: its export is gone
            await a.fed.join()
            assert await next_event(seen, MembershipEvent("joined", "uav-a"))
        await until(lambda: len(a.exporter.running) == 1, "created again by itself")
        assert a.exporter.running[0] is not None and first not in a.fed.exports
        await b.fed.cancel_stream("uav-a", first)  # the only id the user ever got
        assert a.exporter.running == [] and b.fed._durable["uav-a"] == {}


async def test_a_durable_stream_that_still_runs_is_not_asked_for_again() -> None:
    # the provider only left and came back: its export still runs, nothing to re-create
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        first = await b.fed.create_stream("uav-a", ["car5-state"], durable=True)
        async with b.fed.membership() as seen:
            await a.fed.leave()
            await next_event(seen, MembershipEvent("left", "uav-a"))
            await a.fed.join()
            await next_event(seen, MembershipEvent("joined", "uav-a"))
        await asyncio.sleep(0.2)  # the re-ask ran (refused: it still runs) and gave up at once
        assert len(a.exporter.running) == 1 and b.fed._durable["uav-a"][first].current == first


async def test_the_receiver_is_told_when_its_exports_lease_expires() -> None:
    ended: list[tuple[str, str]] = []
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        _, a = await net.platform("uav-a")
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a", lease=1.0)
        imp = await net.importer("uav-b", translate=agreed(SEM))
        imp.on_export_ended = lambda sender, label: ended.append((sender, label))
        export = exp.start_exporting(LOCAL, SEM, "uav-b")
        src.push(0)
        rec = await until(lambda: imp.get("uav-a", SEM), "the first sample")
        real = imp._report

        async def stalled(*_: Any, **__: Any) -> None:
            """The receiver does not report (a long pause): its lease runs out."""

        imp._report = stalled  # type: ignore[method-assign]
        await until(lambda: export.ended, "the lease expired", 5.0)
        imp._report = real  # type: ignore[method-assign]
        await until(lambda: rec.ended, "the receiver told", 5.0)
        assert ended == [("uav-a", SEM)] and export.ended.startswith("lease-expired")


async def test_an_idle_stream_created_again_after_its_sender_was_gone_keeps_its_lease() -> None:
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        _, a = await net.platform("uav-a")
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a", lease=1.0)
        imp = await net.importer("uav-b", translate=agreed(SEM))
        first = exp.start_exporting(LOCAL, SEM, "uav-b")
        src.push(1)
        rec = await until(lambda: imp.get("uav-a", SEM), "the first sample")
        # what the importer does when uav-a's token goes (a router restart), then returns
        imp._gone.add("uav-a")
        imp._end(rec)
        imp._gone.discard("uav-a")
        await exp.stop(first)
        again = exp.start_exporting(LOCAL, SEM, "uav-b")  # created again; the source is quiet
        await asyncio.sleep(2.5)  # more than two leases
        assert again.active, again.ended


async def test_a_new_export_does_not_inherit_the_losses_of_the_old_one() -> None:
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        ta, a = await net.platform("uav-a")
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a")
        imp = await net.importer("uav-b", translate=agreed(SEM))
        drop = False
        publish = ta.publish

        async def lossy(key: str, payload: bytes, *args: Any, **kwargs: Any) -> Any:
            if drop and "/stream/" in key:
                return None  # lost on the way
            return await publish(key, payload, *args, **kwargs)

        ta.publish = lossy  # type: ignore[method-assign]
        old = exp.start_exporting(LOCAL, SEM, "uav-b")
        for i in range(10):
            src.push(i)
        await until(lambda: (r := imp.get("uav-a", SEM)) is not None and r.injected == 10, "10")
        drop = True
        for i in range(10):
            src.push(i)
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)
        drop = False
        for i in range(10):
            src.push(i)
        await until(lambda: old.dropped.get("lost-in-transit") == 10, "the old one told of 10")
        await exp.stop(old)
        new = exp.start_exporting(LOCAL, SEM, "uav-b")
        for i in range(10):
            src.push(i)
        rec = imp.get("uav-a", SEM)
        assert rec is not None
        await until(lambda: rec.injected == 30, "the new one delivered its 10")
        await asyncio.sleep(1.2)  # two reports
        assert new.dropped == {} and rec.lost == 10  # the receiver's total stays


def test_an_export_lease_shorter_than_four_report_intervals_is_refused() -> None:
    base = {"name": "a", "federation": "f", "key": "k", "trust": "t"}
    base |= {"vocabulary": {}, "mapping": {}}
    with pytest.raises(PlatformConfigError, match="export_lease"):
        PlatformConfig.from_dict({**base, "export_lease": 0.3})
    assert PlatformConfig.from_dict({**base, "export_lease": 2.0}).export_lease == 2.0


async def test_send_failures_recovered_from_history_are_no_longer_counted_dropped() -> None:
    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        ta, a = await net.platform("uav-a")
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a")
        imp = await net.importer("uav-b", translate=agreed(SEM), report_interval=0.05)
        mode = "ok"
        publish = ta.publish

        async def flaky(key: str, payload: bytes, *args: Any, **kwargs: Any) -> Any:
            if "/stream/" in key and mode == "raise":
                raise RuntimeError("congested")  # a send failure: counted at the sender
            if "/stream/" in key and mode == "drop":
                return None  # lost on the way, silently: the receiver counts it
            return await publish(key, payload, *args, **kwargs)

        ta.publish = flaky  # type: ignore[method-assign]
        export = exp.start_exporting(LOCAL, SEM, "uav-b", history=10)

        def rec() -> Any:
            return imp.get("uav-a", SEM)

        async def push(n: int) -> None:
            for i in range(n):
                src.push(i)
                await asyncio.sleep(0.005)
            await asyncio.sleep(0.05)

        await push(5)
        mode = "raise"
        await push(10)
        mode = "ok"
        await push(5)
        await until(lambda: rec().recovered == 10 and rec().lost == 0, "the 10 failed resent")
        assert "send-failed" not in export.dropped  # they arrived after all
        mode = "drop"
        await push(30)
        mode = "ok"
        await push(5)
        await until(lambda: rec().recovered == 20, "10 of the 30 resent (history 10)")
        await until(
            lambda: export.dropped.get("lost-in-transit", 0) == rec().lost == 20,
            "the sender counts what the receiver lost",
        )
