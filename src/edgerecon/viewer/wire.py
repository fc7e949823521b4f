"""A minimal client of viser's wire protocol: what a browser receives, decoded.

Used by the protocol-level tests and by ``benchmarks/bench_viewer.py`` as a stand-in for a
browser on another device (``python -m edgerecon.viewer.wire PORT`` receives and decodes
until it is terminated, then prints what it received as JSON). Frame layout (viser 1.1):
8 bytes msgpack size, 8 bytes compressed size, zstd-compressed msgpack
``{"messages", "binaryBufferLengths"}``, then the binary buffers, each 8-byte aligned;
arrays in messages are ``{"__binary_index": i, "dtype": ...}`` placeholders.
"""

from __future__ import annotations

import json
import signal
import sys
import time
from collections.abc import Iterator
from typing import Any

import msgspec
import numpy as np
import viser
import zstandard
from websockets.sync.client import connect
from websockets.typing import Subprotocol


class WireClient:
    """Connects to a viser server on 127.0.0.1 like the web client does."""

    def __init__(self, port: int) -> None:
        self.bytes_received = 0
        self.ws = connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=[Subprotocol(f"viser-v{viser.__version__}")],
            max_size=None,
            proxy=None,
        )

    def close(self) -> None:
        self.ws.close()

    def messages(self, timeout_s: float) -> Iterator[tuple[dict[str, Any], list[bytes]]]:
        """Decoded messages (dict, binary buffers of its window) until ``timeout_s``."""
        end = time.monotonic() + timeout_s
        while (left := end - time.monotonic()) > 0:
            try:
                raw = self.ws.recv(timeout=left)
            except TimeoutError:
                return
            assert isinstance(raw, bytes)
            self.bytes_received += len(raw)
            n_inner = int.from_bytes(raw[:8], "little")
            n_comp = int.from_bytes(raw[8:16], "little")
            inner = zstandard.ZstdDecompressor().decompress(
                raw[16 : 16 + n_comp], max_output_size=n_inner
            )
            payload = msgspec.msgpack.decode(inner)
            offset = 16 + n_comp
            buffers = []
            for length in payload["binaryBufferLengths"]:
                offset += (8 - offset % 8) % 8
                buffers.append(raw[offset : offset + length])
                offset += length
            for message in payload["messages"]:
                yield message, buffers

    def next_cloud(self, name: str, timeout_s: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(points, colours) of the next point-cloud message for scene node ``name``."""
        for message, buffers in self.messages(timeout_s):
            if message.get("type") == "PointCloudMessage" and message.get("name") == name:
                props = message["props"]
                return _array(props["points"], buffers).reshape(-1, 3), _array(
                    props["colors"], buffers
                ).reshape(-1, 3)
        return None


def _array(value: Any, buffers: list[bytes]) -> np.ndarray:
    if isinstance(value, dict) and "__binary_index" in value:
        return np.frombuffer(buffers[value["__binary_index"]], dtype=value["dtype"])
    return np.asarray(value)


def main(argv: list[str] | None = None) -> int:
    """Receive from the viser server on 127.0.0.1:PORT until SIGTERM / SIGINT; print
    ``{"clouds": n, "points": total, "bytes": total}``."""
    port = int((argv or sys.argv[1:])[0])
    stop = {"now": False}

    def handler(*_: object) -> None:
        stop["now"] = True

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
    client = WireClient(port)
    clouds = points = 0
    try:
        while not stop["now"]:
            for message, buffers in client.messages(0.5):
                if message.get("type") == "PointCloudMessage":
                    clouds += 1
                    points += len(_array(message["props"]["points"], buffers)) // 3
    except Exception:  # a closed server ends the run like a signal
        pass
    finally:
        client.close()
    print(json.dumps({"clouds": clouds, "points": points, "bytes": client.bytes_received}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
