"""Whether Zenoh keeps the order of one sender's messages on two keys at one receiving
session (docs/architecture.md, "Order on the bus"): a router on a loopback port, a
sending session putting N pairs (key A then key B, the i-th pair carrying i), and a
receiving session, first with one subscriber per key (as a service subscribes), then
with one subscriber on a pattern covering both. Prints, for each, how many pairs
arrived second-first. Prints only; runs in seconds."""

from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import queue
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _stats import cpu_model  # noqa: E402

from cli.supervisor import free_port  # noqa: E402
from shared.net.bus import Bus  # noqa: E402

KEY_A, KEY_B = "probe/order/status/learner", "probe/order/action/actor"


def swapped(endpoint: str, pairs: int, one_subscriber: bool, publisher: bool) -> int:
    """Pairs whose B arrived before their A."""
    got: queue.Queue[tuple[str, int]] = queue.Queue()
    with Bus([endpoint]) as send, Bus([endpoint]) as recv:
        if one_subscriber:
            recv.subscribe("probe/order/**", lambda k, p: got.put((k, int(p))))
        else:
            recv.subscribe(KEY_A, lambda k, p: got.put((k, int(p))))
            recv.subscribe(KEY_B, lambda k, p: got.put((k, int(p))))
        time.sleep(1.0)  # (the subscriptions known to the router)
        put_b = send.publisher(KEY_B) if publisher else (lambda p: send.put(KEY_B, p))
        for i in range(pairs):
            send.put(KEY_A, str(i).encode())
            put_b(str(i).encode())
        where: dict[tuple[str, int], int] = {}
        deadline = time.monotonic() + 30
        while len(where) < 2 * pairs and time.monotonic() < deadline:
            with contextlib.suppress(queue.Empty):
                where[got.get(timeout=1.0)] = len(where)
    if len(where) < 2 * pairs:
        raise SystemExit(f"only {len(where)} of {2 * pairs} messages arrived")
    return sum(where[(KEY_B, i)] < where[(KEY_A, i)] for i in range(pairs))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--pairs", type=int, default=2000, help="pairs sent per case")
    args = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    zenoh = importlib.metadata.version("eclipse-zenoh")
    print(f"CPU: {cpu_model()}; zenoh {zenoh}; {args.pairs} pairs a case")
    with Bus.router(listen=[endpoint]):
        time.sleep(0.5)
        for one, pub in ((False, False), (False, True), (True, False), (True, True)):
            n = swapped(endpoint, args.pairs, one, pub)
            subs = "one subscriber on both keys" if one else "a subscriber per key"
            how = "put, then a declared publisher" if pub else "two session puts"
            print(f"{subs:<28} {how:<32} {n:5d} of {args.pairs} pairs second-first")


if __name__ == "__main__":
    main()
