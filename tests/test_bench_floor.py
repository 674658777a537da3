"""The ACL floor benchmark (``python -m bench._acl_floor``) run small, so it cannot rot unnoticed.

Every variant answers between two spawned processes, the CPU figures are read, and the
BENCH lines come out in the form CI greps for; the plain envelope it seals refuses what
ours refuses first (a changed byte, a replayed counter), so the crypto variant does that
work and no less.
"""

from __future__ import annotations

import re

import pytest
from cryptography.exceptions import InvalidTag

from bench import fmt
from bench._acl_floor import KEYS, VARIANTS, _Envelopes, measure, print_floor, summarise

BENCH_LINE = re.compile(
    r"^BENCH [a-z0-9-]+ ours=\S+ [a-z0-9-]+=\S+ ratio=\d+\.\d\d unit=\S+ better=(higher|lower)$"
)


@pytest.mark.timeout(120)
def test_a_small_run_answers_every_variant(capsys: pytest.CaptureFixture[str]) -> None:
    res = measure(20, 1, block=10, warmup=5)
    for name in VARIANTS:
        (one,) = res[name]
        assert len(one["rtts"]) == 20 and min(one["rtts"]) > 0
        assert one["all_a"] > 0 and one["all_b"] > 0
    lines = print_floor(res)
    out = capsys.readouterr().out
    assert [line.split()[1] for line in lines] == [
        f"acl-floor-{name}-vs-get" for name in VARIANTS if name != "get"
    ]
    rows = summarise(res)
    for line in lines:
        assert BENCH_LINE.match(line), line
        assert line in out
        # ours= holds the floor variant, the peer raw get: the ratio is variant / get
        fields = dict(f.split("=", 1) for f in line.split()[2:])
        variant = line.split()[1].removeprefix("acl-floor-").removesuffix("-vs-get")
        assert fields["ours"] == fmt(rows[variant]["median"] / 1e3), line
        assert fields["zenoh-get"] == fmt(rows["get"]["median"] / 1e3), line
        # the ratio of the medians themselves, to its two decimals (the printed figures
        # are rounded to three digits: their quotient may differ by more than that)
        exact = rows[variant]["median"] / rows["get"]["median"]
        assert float(fields["ratio"]) == pytest.approx(exact, abs=0.0051), line
    # bench.acl measures ours in turns with them: its line comes last (a's rounds stand in)
    with_ours = print_floor({**res, "ours": res["get"]})
    assert [line.split()[1] for line in with_ours] == [
        *(line.split()[1] for line in lines),
        "acl-floor-ours-vs-get",
    ]


def test_the_plain_envelope_opens_once_and_only_unchanged() -> None:
    a = _Envelopes("bench-a", "bench-b", KEYS[0], KEYS[1])
    b = _Envelopes("bench-b", "bench-a", KEYS[1], KEYS[0])
    first, second = a.seal(b'{"x": 1}'), a.seal(b'{"x": 2}')
    assert b.open(second) == b'{"x": 2}'
    with pytest.raises(ValueError, match="replayed"):
        b.open(first)  # an older counter than one already opened
    tampered = bytearray(a.seal(b'{"x": 3}'))
    i = tampered.index(b'"box":"') + 8
    tampered[i] = ord("A") if tampered[i] != ord("A") else ord("B")
    with pytest.raises((InvalidTag, ValueError)):
        b.open(bytes(tampered))
