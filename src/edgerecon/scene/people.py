"""People in a frame, from a learned segmentation model: the cue the background models lack.

A background model cannot tell a person who sits still from the first frame from the chair
they sit on: both were there when it learned (``scene.stream``: without an empty-scene clip
the models start from the stream itself). A person segmentation model can. MediaPipe's
selfie segmentation network (its landscape variant: a 256x144 RGB input, one sigmoid output
per pixel, 250 kB, Apache-2.0) runs in OpenCV's own DNN module (``cv2.dnn``, TFLite
importer): no new runtime, 2-7 ms per camera at the scene stage's working size on this
2-core machine. :class:`PersonSegmenter` wraps it (every frame stretched to the input:
portrait crops of real captures gave the same masks as letterboxed ones);
``RigForeground.segment`` adds its
masks to the models' before the visual hull, which keeps only what several cameras agree
on (a person seen by one camera alone, or a poster that one camera takes for a person, has
no hull).

The model is not part of edgerecon: :func:`fetch_person_model` (``edgerecon models
fetch``) takes it from MediaPipe's own wheel on the package index (``pip download``, no
other network), checks its SHA-256 and keeps it in :func:`models_dir`. Without it the
scene stage is what it was (``ForegroundConfig.person_model = "auto"`` uses the model when
it is there; ``"off"`` never; a path names a file).

What it can do and cannot: people at any distance the rig sees them at a few dozen working
pixels (utrecht4cam's seated person across a 10 m room, caliscope_charuco's at 2 m); it
also marks what a person holds and sits on where they merge in the image (the chair's
back, the board), and animals now and then; mannequins and rendered actors only in parts.
"""

from __future__ import annotations

import hashlib
import logging
import os
import subprocess
import sys
import tempfile
import threading
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.types import EdgereconError, Mask

logger = logging.getLogger(__name__)

#: The model's file name in :func:`models_dir`.
PERSON_MODEL_FILE = "selfie_segmentation_landscape.tflite"
#: Its SHA-256 (the same file in MediaPipe 0.10.14-0.10.21).
PERSON_MODEL_SHA256 = "a77d03f4659b9f6b6c1f5106947bf40e99d7655094b6527f214ea7d451106edd"
#: Where it is inside MediaPipe's wheel.
PERSON_MODEL_MEMBER = f"mediapipe/modules/selfie_segmentation/{PERSON_MODEL_FILE}"
#: MediaPipe releases whose wheels hold it, tried in order (later ones ship no models).
PERSON_MODEL_SOURCES = ("mediapipe==0.10.21", "mediapipe==0.10.14")
#: The network's input (width, height).
_INPUT_SIZE = (256, 144)


def models_dir() -> Path:
    """Where fetched models live: ``$EDGERECON_MODELS``, else ``$XDG_CACHE_HOME/edgerecon/
    models``, else ``~/.cache/edgerecon/models``."""
    explicit = os.environ.get("EDGERECON_MODELS")
    if explicit:
        return Path(explicit).expanduser()
    cache = os.environ.get("XDG_CACHE_HOME")
    base = Path(cache).expanduser() if cache else Path.home() / ".cache"
    return base / "edgerecon" / "models"


def person_model_path(setting: str = "auto") -> Path | None:
    """The model file a ``ForegroundConfig.person_model`` setting names: ``"off"`` none,
    ``"auto"`` the fetched one when it is there, ``"on"`` the fetched one (which must be
    there: ``EdgereconError``), anything else a path (which must exist)."""
    if setting == "off":
        return None
    if setting in ("auto", "on"):
        path = models_dir() / PERSON_MODEL_FILE
        if path.is_file() or setting == "auto":
            return path if path.is_file() else None
        raise EdgereconError(
            f"person_model 'on': no model in {models_dir()} (`edgerecon models fetch` gets "
            f"it; 'auto' runs without when it is not there)"
        )
    path = Path(setting).expanduser()
    if not path.is_file():
        raise EdgereconError(
            f"person_model {setting!r}: no such file (`edgerecon models fetch` gets the "
            f"model; 'auto' uses it when fetched, 'off' runs without)"
        )
    return path


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def is_measured_model(path: Path) -> bool:
    """Whether ``path`` is the person model edgerecon was measured with (its SHA-256)."""
    return sha256_of(path) == PERSON_MODEL_SHA256


def _extract(wheel: Path, dest: Path, expected_sha256: str) -> Path:
    """The model out of a MediaPipe wheel into ``dest`` (atomically), its hash checked."""
    try:
        with zipfile.ZipFile(wheel) as zf:
            try:
                data = zf.read(PERSON_MODEL_MEMBER)
            except KeyError:
                raise EdgereconError(
                    f"{wheel.name} holds no {PERSON_MODEL_MEMBER} (MediaPipe releases after "
                    f"0.10.21 ship no models)"
                ) from None
    except zipfile.BadZipFile as exc:
        raise EdgereconError(f"{wheel}: not a wheel ({exc})") from None
    digest = hashlib.sha256(data).hexdigest()
    if digest != expected_sha256:
        raise EdgereconError(
            f"{wheel.name}: {PERSON_MODEL_FILE} has SHA-256 {digest}, expected "
            f"{expected_sha256}: not the model edgerecon was measured with"
        )
    dest.mkdir(parents=True, exist_ok=True)
    target = dest / PERSON_MODEL_FILE
    tmp = target.with_suffix(".part")
    tmp.write_bytes(data)
    os.replace(tmp, target)
    (dest / f"{PERSON_MODEL_FILE}.SOURCE.txt").write_text(
        f"{PERSON_MODEL_FILE}: MediaPipe's selfie segmentation model (landscape), "
        f"Apache License 2.0, Google LLC.\nTaken from {wheel.name} ({PERSON_MODEL_MEMBER}), "
        f"SHA-256 {digest}.\n"
    )
    return target


def fetch_person_model(
    dest: Path | None = None,
    *,
    wheel: Path | None = None,
    expected_sha256: str = PERSON_MODEL_SHA256,
) -> Path:
    """Put the person model in ``dest`` (default :func:`models_dir`) and return its path:
    from ``wheel`` (a MediaPipe wheel already downloaded, for machines without the package
    index), else ``pip download`` of one of ``PERSON_MODEL_SOURCES`` (the Linux x86-64
    wheel whatever this machine is: the model is the same file in each). A model already
    there with the right hash is kept. ``EdgereconError`` when it cannot be had."""
    dest = models_dir() if dest is None else dest
    target = dest / PERSON_MODEL_FILE
    if wheel is None and target.is_file() and sha256_of(target) == expected_sha256:
        return target
    if wheel is not None:
        return _extract(wheel, dest, expected_sha256)
    failures: list[str] = []
    with tempfile.TemporaryDirectory(prefix="edgerecon-models-") as tmp:
        for spec in PERSON_MODEL_SOURCES:
            cmd = [
                sys.executable,
                "-m",
                "pip",
                "download",
                "--no-deps",
                "--only-binary=:all:",
                "--platform",
                "manylinux_2_28_x86_64",
                "--python-version",
                "3.11",
                "--implementation",
                "cp",
                "--abi",
                "cp311",
                "--dest",
                tmp,
                spec,
            ]
            logger.warning("fetching %s's person model: %s", spec, " ".join(cmd[1:]))
            proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
            wheels = sorted(Path(tmp).glob("mediapipe-*.whl"))
            if proc.returncode != 0 or not wheels:
                tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no wheel"]
                failures.append(f"{spec}: {tail[0]}")
                continue
            return _extract(wheels[-1], dest, expected_sha256)
    raise EdgereconError(
        "could not fetch the person model (" + "; ".join(failures) + "): download a "
        "MediaPipe 0.10.14-0.10.21 wheel elsewhere and give it to `edgerecon models fetch "
        "--wheel FILE`"
    )


@dataclass(frozen=True)
class PersonSegmenter:
    """Per-pixel person probability of BGR frames (see module docstring). Thread-safe: one
    network per thread (``cv2.dnn.Net`` keeps its buffers between calls)."""

    path: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "_local", threading.local())
        self._net()  # a file OpenCV cannot read fails here, not in a task

    def _net(self) -> Any:
        local = self._local  # type: ignore[attr-defined]
        net = getattr(local, "net", None)
        if net is None:
            try:
                net = cv2.dnn.readNetFromTFLite(str(self.path))
            except cv2.error as exc:
                raise EdgereconError(
                    f"person model {self.path}: OpenCV cannot read it ({exc})"
                ) from None
            local.net = net
        return net

    def probability(self, image: NDArray[Any]) -> NDArray[np.float32]:
        """(h, w) person probability in [0, 1] of a BGR frame (uint8, or float32 in 0..255
        like the background models' working images) of any size."""
        h, w = image.shape[:2]
        # Stretched to the input, whatever the frame's shape: people stay upright (a
        # portrait frame turned a quarter would lay them down), and on portrait crops of
        # real captures the stretched masks match the letterboxed ones while a person far
        # away keeps more input pixels.
        blob = cv2.dnn.blobFromImage(
            image, 1.0 / 255.0, _INPUT_SIZE, swapRB=True, crop=False, ddepth=cv2.CV_32F
        )
        net = self._net()
        net.setInput(blob)
        out = np.asarray(net.forward(), np.float32).reshape(_INPUT_SIZE[1], _INPUT_SIZE[0])
        prob = np.asarray(cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR), np.float32)
        return np.clip(prob, 0.0, 1.0, out=prob)

    def mask(self, image: NDArray[Any], threshold: float = 0.5) -> Mask:
        """(h, w) pixels more likely a person than not (``threshold``)."""
        return np.asarray(self.probability(image) > threshold, bool)


_segmenters: dict[Path, PersonSegmenter] = {}
_refused: set[Path] = set()
_segmenters_lock = threading.Lock()


def person_segmenter(setting: str = "auto") -> PersonSegmenter | None:
    """The segmenter a ``ForegroundConfig.person_model`` setting asks for (one per file and
    process), None without a model (``"auto"`` before ``edgerecon models fetch``). The
    fetched model (``"auto"``, ``"on"``) must have its SHA-256; one that does not, or that
    OpenCV cannot read, is an ``EdgereconError`` for ``"on"`` and a path, and for ``"auto"``
    a warning (once per process) and no person model: a damaged cache never fails tasks."""
    path = person_model_path(setting)
    if path is None:
        return None
    with _segmenters_lock:
        seg = _segmenters.get(path)
        if seg is not None:
            return seg
        if path in _refused and setting == "auto":
            return None
        try:
            if setting in ("auto", "on") and not is_measured_model(path):
                raise EdgereconError(
                    f"{path} is not the person model edgerecon was measured with (its SHA-256 "
                    f"differs): `edgerecon models fetch` again"
                )
            seg = _segmenters[path] = PersonSegmenter(path)
        except EdgereconError as exc:
            if setting != "auto":
                raise
            _refused.add(path)
            logger.warning("the person model is left out: %s", exc)
            return None
        return seg


__all__ = [
    "PERSON_MODEL_FILE",
    "PERSON_MODEL_SHA256",
    "PersonSegmenter",
    "fetch_person_model",
    "is_measured_model",
    "models_dir",
    "person_model_path",
    "person_segmenter",
]
