"""Drive Debian's headless Chromium through the DevTools protocol, for page tests that
type and click.

Chromium runs with `--remote-debugging-pipe`: it reads protocol messages (JSON, each
ended by a NUL byte) on fd 3 and writes on fd 4, so no port is opened and no library
beyond the standard one is needed. Typing goes through `Input.insertText` into the
focused element and clicks are mouse events at the element's centre, as a person's
would be: the page's own handlers do the rest.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any

CHROMIUM = Path("/usr/bin/chromium")
# Headless and quiet: without the background-networking flags Chromium's connections
# are refused by this machine's closed network, many at a time.
HEADLESS_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    "--hide-scrollbars",
)


class CdpError(RuntimeError):
    pass


class Browser:
    """One headless Chromium with one page; `close()` ends it (by its PID)."""

    def __init__(self, profile: Path, width: int = 1400, height: int = 1800) -> None:
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()
        profile.mkdir(parents=True, exist_ok=True)
        args = [
            *HEADLESS_FLAGS,
            "--remote-debugging-pipe",
            f"--user-data-dir={profile}",
            f"--window-size={width},{height}",
            "about:blank",
        ]
        # The pipe ends go to fds 3 and 4 of the child, where Chromium expects them.
        shell = f'exec 3<&{to_chrome_r} 4>&{from_chrome_w}; exec "$0" "$@"'
        self.proc = subprocess.Popen(
            ["/bin/bash", "-c", shell, str(CHROMIUM), *args],
            pass_fds=(to_chrome_r, from_chrome_w),
            stdout=subprocess.DEVNULL,
            stderr=(profile / "chromium.log").open("wb"),
        )
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buf = b""
        self._next_id = 0
        self.events: list[dict[str, Any]] = []
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)[
            "sessionId"
        ]
        self.call("Page.enable", session=self.session)
        self.call("Runtime.enable", session=self.session)

    # ------------------------------------------------------------------ the protocol
    def _read_message(self, timeout: float) -> dict[str, Any]:
        import select

        deadline = time.monotonic() + timeout
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise CdpError("no answer from Chromium in time")
            ready, _, _ = select.select([self._from_chrome], [], [], left)
            if ready:
                chunk = os.read(self._from_chrome, 1 << 16)
                if not chunk:
                    raise CdpError(f"Chromium closed the pipe (exit {self.proc.poll()})")
                self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        return json.loads(raw)

    def call(self, method: str, session: str | None = None, timeout: float = 30, **params):
        self._next_id += 1
        msg: dict[str, Any] = {"id": self._next_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        os.write(self._to_chrome, json.dumps(msg).encode() + b"\0")
        while True:
            answer = self._read_message(timeout)
            if answer.get("id") != self._next_id:
                self.events.append(answer)
                continue
            if "error" in answer:
                raise CdpError(f"{method}: {answer['error']}")
            return answer.get("result", {})

    # ------------------------------------------------------------------ the page
    def page(self, method: str, **params) -> dict[str, Any]:
        return self.call(method, session=self.session, **params)

    def js(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (promises awaited)."""
        out = self.page(
            "Runtime.evaluate", expression=expression, awaitPromise=True, returnByValue=True
        )
        if "exceptionDetails" in out:
            raise CdpError(f"{expression}: {out['exceptionDetails']}")
        return out["result"].get("value")

    def goto(self, url: str) -> None:
        self.page("Page.navigate", url=url)
        self.wait("document.readyState === 'complete'", what=f"{url} loaded")

    def wait(self, expression: str, timeout: float = 30, what: str | None = None) -> Any:
        """Poll until the expression is truthy in the page; its value."""
        deadline = time.monotonic() + timeout
        while True:
            value = self.js(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"timed out waiting for {what or expression}")
            time.sleep(0.2)

    def click(self, selector: str) -> None:
        """A left click at the centre of the element (scrolled into view first)."""
        box = self.js(
            f"""(() => {{ const e = document.querySelector({json.dumps(selector)});
              if (!e) return null; e.scrollIntoView({{block: "center"}});
              const r = e.getBoundingClientRect();
              return [r.left + r.width / 2, r.top + r.height / 2]; }})()"""
        )
        if box is None:
            raise CdpError(f"no element {selector}")
        x, y = box
        for kind in ("mousePressed", "mouseReleased"):
            self.page("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)

    def type(self, selector: str, text: str) -> None:
        """Replace the field's text as typing would: focus, select all, insert."""
        found = self.js(
            f"""(() => {{ const e = document.querySelector({json.dumps(selector)});
              if (!e) return false; e.focus(); e.select(); return true; }})()"""
        )
        if not found:
            raise CdpError(f"no field {selector}")
        self.page("Input.insertText", text=text)

    def choose(self, selector: str, value: str) -> None:
        """Pick an option of a <select> (as the keyboard would: the change event fires)."""
        ok = self.js(
            f"""(() => {{ const s = document.querySelector({json.dumps(selector)});
              if (!s || ![...s.options].some(o => o.value === {json.dumps(value)})) return false;
              s.focus(); s.value = {json.dumps(value)};
              s.dispatchEvent(new Event("input", {{bubbles: true}}));
              s.dispatchEvent(new Event("change", {{bubbles: true}})); return true; }})()"""
        )
        if not ok:
            raise CdpError(f"no option {value!r} in {selector}")

    def screenshot(self, path: Path) -> Path:
        data = self.page("Page.captureScreenshot", format="png", captureBeyondViewport=True)
        path.write_bytes(base64.b64decode(data["data"]))
        return path

    def close(self) -> None:
        with contextlib.suppress(CdpError, OSError):
            self.call("Browser.close", timeout=5)
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self._to_chrome, self._from_chrome):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
