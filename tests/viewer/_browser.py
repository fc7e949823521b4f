"""Headless Chromium driven over the DevTools protocol: open a page, take screenshots.

Debian's ``chromium`` renders WebGL in software (SwiftShader) with the flags below, which
is all a screenshot test needs: no GPU, no display. ``.ci/run`` installs it.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
import pytest
from websockets.sync.client import connect

FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--use-gl=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--remote-debugging-port=0",
]


def chromium_or_skip() -> str:
    """The Chromium binary; skips the test when there is none, unless
    ``EDGERECON_REQUIRE_BROWSER=1`` (set by ``.ci/run``, which installs it) makes that a
    failure."""
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        path = shutil.which(name)
        if path:
            return path
    if os.environ.get("EDGERECON_REQUIRE_BROWSER") == "1":
        pytest.fail("EDGERECON_REQUIRE_BROWSER=1 but no chromium on PATH")
    pytest.skip("no chromium on PATH (apt-get install chromium; .ci/run does)")


class Browser:
    """One headless Chromium with one page, controlled over the DevTools protocol."""

    def __init__(self, binary: str, url: str, width: int = 1280, height: int = 800) -> None:
        self.width, self.height = width, height
        self._profile = tempfile.mkdtemp(prefix="edgerecon-chromium-")
        self.proc = subprocess.Popen(
            [
                binary,
                *FLAGS,
                f"--user-data-dir={self._profile}",
                f"--window-size={width},{height}",
                url,
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        endpoint = self._devtools_endpoint(timeout_s=60)
        port = endpoint.split(":")[2].split("/")[0]
        opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
        pages: list[dict[str, Any]] = []
        end = time.monotonic() + 30
        while not pages and time.monotonic() < end:
            with opener.open(f"http://127.0.0.1:{port}/json/list", timeout=30) as r:
                pages = [t for t in json.load(r) if t["type"] == "page"]
            time.sleep(0.2)
        if not pages:
            self.close()
            raise RuntimeError(f"chromium opened no page for {url}")
        self.ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, proxy=None)
        self._id = 0
        self.call(
            "Emulation.setDeviceMetricsOverride",
            width=width,
            height=height,
            deviceScaleFactor=1,
            mobile=False,
        )

    def _devtools_endpoint(self, timeout_s: float) -> str:
        found: list[str] = []
        ready = threading.Event()

        def read() -> None:
            assert self.proc.stderr is not None
            for line in self.proc.stderr:  # keep draining: a full pipe would block Chromium
                if not found and "DevTools listening on" in line:
                    found.append(line.split("on", 1)[1].strip())
                    ready.set()

        threading.Thread(target=read, daemon=True).start()
        if not ready.wait(timeout_s):
            self.close()
            raise RuntimeError("chromium did not start its DevTools endpoint")
        return found[0]

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv(timeout=120))
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return dict(reply.get("result", {}))

    def screenshot(self) -> np.ndarray:
        """The page as a BGR image."""
        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        assert image is not None
        return image

    def wait_for(
        self, predicate: Callable[[np.ndarray], bool], timeout_s: float, every_s: float = 1.0
    ) -> np.ndarray:
        """Screenshots until ``predicate(image)`` holds or time is up; the last one."""
        end = time.monotonic() + timeout_s
        while True:
            image = self.screenshot()
            if predicate(image) or time.monotonic() > end:
                return image
            time.sleep(every_s)

    def close(self) -> None:
        try:
            if hasattr(self, "ws"):
                self.ws.close()
        finally:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
