"""The two forms of an ACL envelope, seal and open: ``python -m bench._acl_forms``.

One session made by a real handshake (encrypted, the default policy), an ACL message of
``bench.acl.ACL_BYTES`` bytes. Each round seals N envelopes in the JSON form and N in the
binary form (`SessionTable.seal` / `seal_binary`), then opens them (`SessionTable.open`,
which reads both), in alternated order, and notes each step's thread CPU per envelope:
load on the machine slows both forms alike. Prints each form's median µs, the envelope's
size and binary over JSON.

``--form json|binary [N]`` seals and opens N envelopes of one form only and prints
nothing else: a fixed workload for ``valgrind --tool=callgrind`` (instruction counts,
which other work on the machine does not change).
"""

from __future__ import annotations

import statistics
import sys
import time

N = 2000
ROUNDS = 15


def _tables() -> tuple[object, object, bytes]:
    """Sender's and receiver's session tables (one session) and the message's JSON."""
    from agents import ACLMessage, Performative
    from agents._security import Handshake, KeyPair, SecurityPolicy, SessionTable, TrustStore
    from bench import acl

    # the replay window moves by one per envelope; the default keeps up with any N
    policy = SecurityPolicy()
    ka, kb = KeyPair.generate(acl.HERE), KeyPair.generate(acl.THERE)
    trust = TrustStore(acl.FEDERATION, {acl.HERE: ka.public_key, acl.THERE: kb.public_key})
    ha, hb = Handshake(ka, trust, policy=policy), Handshake(kb, trust, policy=policy)
    reply, sb = hb.respond(ha.initiate(acl.THERE))
    sa = ha.finish(reply)
    ta = SessionTable(acl.HERE, trust, policy=policy)
    tb = SessionTable(acl.THERE, trust, policy=policy)
    ta.add(sa)
    tb.add(sb)
    probe = ACLMessage(
        performative=Performative.INFORM,
        sender=f"asker@{acl.HERE}",
        receivers=[acl.SINK],
        content={"seq": 12345, "speed": 12.5, "pad": ""},
        ontology="bench-flood",
    )
    pad = "x" * max(0, acl.ACL_BYTES - len(probe.to_json()))
    body = probe.model_copy(update={"content": {"seq": 12345, "speed": 12.5, "pad": pad}})
    return ta, tb, body.to_json()


def measure(n: int = N, rounds: int = ROUNDS) -> dict[str, float]:
    """Each form's median seal and open µs (thread CPU), and its envelope's size."""
    from bench import acl

    ta, tb, body = _tables()
    seal = {"json": ta.seal, "binary": ta.seal_binary}  # type: ignore[attr-defined]
    opened = tb.open  # type: ignore[attr-defined]
    cpu, there = time.thread_time_ns, acl.THERE
    got: dict[str, list[float]] = {f"{f}_{s}": [] for f in seal for s in ("seal", "open")}
    for r in range(rounds):
        for form in ("json", "binary") if r % 2 == 0 else ("binary", "json"):
            make = seal[form]
            t = cpu()
            envelopes = [make(there, body) for _ in range(n)]
            got[f"{form}_seal"].append((cpu() - t) / n / 1e3)
            t = cpu()
            for envelope in envelopes:
                opened(envelope)
            got[f"{form}_open"].append((cpu() - t) / n / 1e3)
    out = {k: statistics.median(v) for k, v in got.items()}
    out["json_bytes"] = len(ta.seal(acl.THERE, body))  # type: ignore[attr-defined]
    out["binary_bytes"] = len(ta.seal_binary(acl.THERE, body))  # type: ignore[attr-defined]
    out["message_bytes"] = len(body)
    return out


def workload(form: str, n: int) -> None:
    """Seal and open ``n`` envelopes of ``form``: what callgrind counts."""
    from bench import acl

    ta, tb, body = _tables()
    seal = ta.seal_binary if form == "binary" else ta.seal  # type: ignore[attr-defined]
    opened = tb.open  # type: ignore[attr-defined]
    for _ in range(n):
        opened(seal(acl.THERE, body))


def main(argv: list[str]) -> None:
    """Parse the command line (see the module's docstring) and print the figures."""
    if argv[:1] in (["-h"], ["--help"]):
        print(__doc__)
        return
    if argv[:1] == ["--form"]:
        workload(argv[1], int(argv[2]) if len(argv) > 2 else N)
        return
    res = measure(int(argv[0]) if argv else N)
    print(f"ACL message {res['message_bytes']:.0f} B, encrypted; thread CPU µs per envelope")
    for form in ("json", "binary"):
        print(
            f"  {form:<7} seal {res[f'{form}_seal']:6.2f}  open {res[f'{form}_open']:6.2f}"
            f"  envelope {res[f'{form}_bytes']:.0f} B"
        )
    for step in ("seal", "open"):
        print(f"  binary / json {step}: {res[f'binary_{step}'] / res[f'json_{step}']:.3f}")
    both = (res["binary_seal"] + res["binary_open"]) / (res["json_seal"] + res["json_open"])
    print(f"  binary / json seal + open: {both:.3f}")


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        main(sys.argv[1:])
