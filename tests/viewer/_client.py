"""A minimal viser wire client: what a browser receives, decoded (protocol-level tests)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import msgspec
import numpy as np
import viser
import zstandard
from websockets.sync.client import connect


class WireClient:
    """Connects to a viser server on 127.0.0.1 like the web client does."""

    def __init__(self, port: int) -> None:
        self.ws = connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=[f"viser-v{viser.__version__}"],  # type: ignore[list-item]
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
