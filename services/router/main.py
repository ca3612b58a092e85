"""The Zenoh router: a Python session in router mode that every service connects to."""

from __future__ import annotations

import logging
import signal
import threading

from shared.bus import Bus

log = logging.getLogger("macb.router")


def serve(listen: list[str]) -> None:
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    with Bus.router(listen):
        log.info("router listening on %s", ", ".join(listen))
        done.wait()
    log.info("router stopped")
