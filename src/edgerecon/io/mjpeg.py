"""MJPEG over HTTP: a reader (:class:`MjpegHttpCapture`) and a loopback server.

``MjpegHttpCapture`` reads an HTTP ``multipart/x-mixed-replace`` JPEG stream (most IP
cameras' MJPEG endpoint) with the interface of ``cv2.VideoCapture`` (``isOpened``, ``grab``,
``retrieve``, ``release``). Live streams use it for ``http(s)://`` URLs instead of OpenCV's
FFmpeg backend, whose opening of a stream holds a process-wide lock: a camera that accepts
the connection but sends nothing would block every other camera's (re)connection for the
open timeout. It also knows each frame's arrival exactly (no read-ahead at opening).
User and password in the URL (``http://user:pass@host/...``) are sent as basic auth.

A loopback MJPEG server: recorded or synthetic frames served as live camera streams.

``MjpegServer`` serves one ``multipart/x-mixed-replace`` stream per camera
(``http://127.0.0.1:PORT/<camera>``), the format of most IP cameras' MJPEG endpoints, which
OpenCV's FFmpeg backend opens like any ``http://`` camera. All cameras tick on one clock at
``fps`` (tick k is sent at ``start + k / fps``), so their frames are synchronized to the
jitter of the machine; ``stalls`` makes a camera send nothing during given windows (a cable
pulled, a camera rebooting) while its connection stays open. With ``stamp=True`` each frame
carries its tick number in a row of black/white squares in its top-left corner
(:func:`read_stamp` reads it back), so a test knows which tick every received frame is.

It exists for tests, benchmarks and trying ``frames.kind = "stream"`` datasets without
cameras; it binds 127.0.0.1 unless told otherwise.
"""

from __future__ import annotations

import base64
import dataclasses
import http.client
import logging
import os
import threading
import time
import urllib.parse
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import cv2
import numpy as np

from edgerecon.types import Image

logger = logging.getLogger(__name__)

#: Bits of the tick stamp and the side of one square, pixels.
STAMP_BITS = 16
STAMP_CELL_PX = 10

FrameProvider = Callable[[int, int], Image]
"""``frame(camera_index, tick)`` -> BGR image of that camera at that tick."""


class MjpegHttpCapture:
    """Frames of an HTTP MJPEG stream, one JPEG part at a time (see module docstring).

    ``isOpened()`` is False when the server cannot be reached within ``open_timeout_s``,
    answers with an error, or does not serve ``multipart/*`` (``not_mjpeg`` then tells the
    caller to try another reader). A part that does not arrive within ``read_timeout_s``
    makes ``grab()`` return False (the caller reconnects).
    """

    def __init__(self, url: str, *, open_timeout_s: float, read_timeout_s: float) -> None:
        self.url = url
        self.not_mjpeg = False
        self.error = ""
        self._conn: http.client.HTTPConnection | None = None
        self._resp: http.client.HTTPResponse | None = None
        self._boundary = b""
        self._data: bytes | None = None
        self._pending_boundary = False
        parts = urllib.parse.urlsplit(url)
        conn_cls = (
            http.client.HTTPSConnection if parts.scheme == "https" else http.client.HTTPConnection
        )
        headers = {"User-Agent": "edgerecon", "Accept": "multipart/x-mixed-replace, */*"}
        if parts.username is not None:
            cred = f"{urllib.parse.unquote(parts.username)}:{urllib.parse.unquote(parts.password or '')}"
            headers["Authorization"] = "Basic " + base64.b64encode(cred.encode()).decode()
        path = parts.path or "/"
        if parts.query:
            path += "?" + parts.query
        try:
            conn = conn_cls(parts.hostname or "", parts.port, timeout=open_timeout_s)
            conn.request("GET", path, headers=headers)
            resp = conn.getresponse()
        except (OSError, http.client.HTTPException) as exc:
            self.error = str(exc)
            return
        ctype = resp.getheader("Content-Type", "") or ""
        if resp.status != 200:
            self.error = f"HTTP {resp.status} {resp.reason}"
            conn.close()
            return
        if not ctype.lower().startswith("multipart/"):
            self.not_mjpeg = True
            self.error = f"content type {ctype!r} is not multipart"
            conn.close()
            return
        boundary = ""
        for field in ctype.split(";")[1:]:
            key, _, value = field.strip().partition("=")
            if key.lower() == "boundary":
                boundary = value.strip().strip('"')
        if boundary.startswith("--"):
            boundary = boundary[2:]
        if not boundary:
            self.error = "multipart stream without a boundary"
            conn.close()
            return
        if conn.sock is not None:
            conn.sock.settimeout(read_timeout_s)
        self._conn, self._resp, self._boundary = conn, resp, b"--" + boundary.encode()

    def isOpened(self) -> bool:
        return self._resp is not None

    def get(self, prop: int) -> float:
        return 0.0

    def grab(self) -> bool:
        """Read the next JPEG part (False: timeout, end of stream or a broken part)."""
        resp = self._resp
        if resp is None:
            return False
        try:
            if self._pending_boundary:  # read with the previous part (no Content-Length)
                self._pending_boundary = False
            else:
                line = resp.readline()
                while line and not line.startswith(self._boundary):
                    line = resp.readline()
                if not line or line.startswith(self._boundary + b"--"):
                    return False
            length = None
            while True:
                header = resp.readline()
                if not header:
                    return False
                if header in (b"\r\n", b"\n"):
                    break
                key, _, value = header.decode("latin-1").partition(":")
                if key.strip().lower() == "content-length":
                    length = int(value.strip())
            if length is not None:
                data = resp.read(length)
                if len(data) < length:
                    return False
            else:  # no length: the part ends at the next boundary
                chunks = []
                while True:
                    line = resp.readline()
                    if not line:
                        return False
                    if line.startswith(self._boundary):
                        self._pending_boundary = True
                        break
                    chunks.append(line)
                data = b"".join(chunks).removesuffix(b"\r\n")
        except (OSError, http.client.HTTPException, ValueError):  # timeouts are OSError
            return False
        self._data = data
        return True

    def retrieve(self) -> tuple[bool, Image | None]:
        if self._data is None:
            return False, None
        image = cv2.imdecode(np.frombuffer(self._data, np.uint8), cv2.IMREAD_COLOR)
        self._data = None
        if image is None:
            return False, None
        return True, np.asarray(image, np.uint8)

    def release(self) -> None:
        if self._conn is not None:
            self._conn.close()
        self._conn = self._resp = None


def stamp(image: Image, tick: int) -> Image:
    """A copy of ``image`` with ``tick`` (mod 2**16) written as 16 black/white squares in
    its top-left corner (most significant bit first)."""
    out = image.copy()
    c = STAMP_CELL_PX
    for bit in range(STAMP_BITS):
        on = (tick >> (STAMP_BITS - 1 - bit)) & 1
        out[0:c, bit * c : (bit + 1) * c] = 255 if on else 0
    return out


def read_stamp(image: Image) -> int:
    """The tick :func:`stamp` wrote into ``image`` (read at the squares' centres, so JPEG
    compression does not change it)."""
    c = STAMP_CELL_PX
    value = 0
    for bit in range(STAMP_BITS):
        y, x = c // 2, bit * c + c // 2
        value = (value << 1) | int(image[y, x].mean() > 127)
    return value


class MjpegServer:
    """Serve ``num_cameras`` synchronized MJPEG streams on one clock (see module docstring).

    ``stalls`` maps a camera index to windows ``(start_s, end_s)``, seconds after
    ``start()``, in which that camera sends nothing.
    """

    def __init__(
        self,
        frame: FrameProvider,
        camera_names: Sequence[str],
        *,
        fps: float = 10.0,
        host: str = "127.0.0.1",
        port: int = 0,
        stalls: Mapping[int, Sequence[tuple[float, float]]] | None = None,
        stamp_ticks: bool = False,
        jpeg_quality: int = 90,
    ) -> None:
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.frame = frame
        self.camera_names = list(camera_names)
        self.fps = float(fps)
        self.stalls = {int(k): list(v) for k, v in (stalls or {}).items()}
        self.stamp_ticks = stamp_ticks
        self.jpeg_quality = int(jpeg_quality)
        self.start_time = 0.0
        self._cache: OrderedDict[tuple[int, int], bytes] = OrderedDict()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.sent = [0] * len(self.camera_names)
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, format: str, *args: object) -> None:
                logger.debug("mjpeg: " + format, *args)

            def do_GET(self) -> None:
                name = self.path.strip("/")
                if name not in server.camera_names:
                    self.send_error(404, f"no camera {name!r}")
                    return
                server._stream(self, server.camera_names.index(name))

        self._httpd = ThreadingHTTPServer((host, port), Handler)
        self._httpd.daemon_threads = True
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return int(self._httpd.server_address[1])

    def url(self, camera: int | str) -> str:
        name = camera if isinstance(camera, str) else self.camera_names[camera]
        return f"http://127.0.0.1:{self.port}/{name}"

    def start(self) -> MjpegServer:
        self.start_time = time.monotonic()
        self._thread = threading.Thread(target=self._httpd.serve_forever, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._httpd.shutdown()
        self._httpd.server_close()

    def __enter__(self) -> MjpegServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def tick_now(self) -> int:
        return int((time.monotonic() - self.start_time) * self.fps)

    def stalled(self, camera: int, t_s: float) -> bool:
        return any(a <= t_s < b for a, b in self.stalls.get(camera, ()))

    def add_stall(self, camera: int, start_s: float, end_s: float) -> None:
        """Make ``camera`` send nothing from ``start_s`` to ``end_s`` seconds after now."""
        now = time.monotonic() - self.start_time
        self.stalls.setdefault(int(camera), []).append((now + start_s, now + end_s))

    def _jpeg(self, camera: int, tick: int) -> bytes:
        key = (camera, tick)
        with self._lock:
            if key in self._cache:
                return self._cache[key]
        image = self.frame(camera, tick)
        if self.stamp_ticks:
            image = stamp(image, tick)
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        data = buf.tobytes()
        with self._lock:
            self._cache[key] = data
            while len(self._cache) > 4 * len(self.camera_names):
                self._cache.popitem(last=False)
        return data

    def _stream(self, handler: BaseHTTPRequestHandler, camera: int) -> None:
        handler.send_response(200)
        handler.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
        handler.send_header("Cache-Control", "no-cache")
        handler.end_headers()
        tick = self.tick_now()
        while not self._stop.is_set():
            due = self.start_time + tick / self.fps
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -1.0 / self.fps:
                tick = self.tick_now()  # fell behind: skip to the present, like a camera
                continue
            if not self.stalled(camera, tick / self.fps):
                data = self._jpeg(camera, tick)
                part = (
                    b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                    + str(len(data)).encode()
                    + b"\r\n\r\n"
                    + data
                    + b"\r\n"
                )
                try:
                    handler.wfile.write(part)
                    handler.wfile.flush()
                except (BrokenPipeError, ConnectionResetError, OSError):
                    return
                self.sent[camera] += 1
            tick += 1


def looped_frames(images: Sequence[Sequence[Image]]) -> FrameProvider:
    """A provider that plays ``images[camera][k]`` in a loop (tick k -> frame k mod n)."""
    n = min(len(seq) for seq in images)
    if n == 0:
        raise ValueError("looped_frames needs at least one frame per camera")
    return lambda camera, tick: images[camera][tick % n]


def solid_frames(width: int, height: int) -> FrameProvider:
    """A provider of plain grey frames whose brightness follows the tick (tests)."""

    def frame(camera: int, tick: int) -> Image:
        return np.full((height, width, 3), 60 + (tick * 7 + camera * 40) % 150, np.uint8)

    return frame


def serve_dataset(
    dataset_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    cameras: Sequence[int] | None = None,
    fps: float = 10.0,
    stalls: Mapping[int, Sequence[tuple[float, float]]] | None = None,
    stamp_ticks: bool = False,
    stream_options: Mapping[str, Any] | None = None,
) -> MjpegServer:
    """Serve a recorded dataset's frames (cameras ``cameras``, all by default, looped) as
    live MJPEG streams and write ``out_dir/dataset.json``: the same rig (restricted to those
    cameras), the dataset's background clip if it has one, and ``frames.kind = "stream"``
    with one URL per camera (and ``stream_options``, e.g. ``sync_tolerance_s``). ``stalls``
    is indexed like ``cameras``. Returns the started server (stop it when done)."""
    from edgerecon.io.dataset import open_dataset, write_dataset_descriptor

    ds = open_dataset(dataset_dir)
    ids = list(range(len(ds.rig))) if cameras is None else [int(i) for i in cameras]
    rig = ds.rig.subset(ids)
    images: list[list[Image]] = [[] for _ in ids]
    with ds.open_frames() as source:
        for frames in source.iter_frames():
            for k, i in enumerate(ids):
                image = frames.images[i]
                assert image is not None
                images[k].append(image)
    server = MjpegServer(
        looped_frames(images), rig.names, fps=fps, stalls=stalls, stamp_ticks=stamp_ticks
    ).start()
    background = None
    if ds.background is not None:
        wanted = set(rig.names)
        background = dataclasses.replace(
            ds.background, cameras=tuple((n, p) for n, p in ds.background.cameras if n in wanted)
        )
    section: dict[str, Any] = {
        "kind": "stream",
        "cameras": {name: server.url(name) for name in rig.names},
        **(stream_options or {}),
    }
    write_dataset_descriptor(
        out_dir, rig=rig, frames=section, background=background, fps=fps, name=f"{ds.name}-live"
    )
    return server
