"""Procedural, tileable surface textures with mip-map pyramids.

Every texture is periodic (its right edge continues its left edge, its bottom its top) so that
surfaces of any size can be covered with ``cv2.remap(..., borderMode=BORDER_WRAP)`` without
seams. Texture coordinates are in metres on the surface; ``Texture.texel_m`` is the size of a
level-0 texel. Textures are albedos (BGR uint8, 255 = white); shading is applied by the
renderer.

The generators give stereo and SIFT something to lock on to (multi-scale noise, tiles, planks,
posters with shapes and text) and, as real rooms do, some weakly textured surfaces (paint).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

#: Number of mip levels below level 0 (each halves the resolution).
MAX_LEVELS = 6
#: Largest number of texels a single ``cv2.remap`` call may produce per row (OpenCV's limit is
#: SHRT_MAX); lookups of many pixels are folded into rows of this width.
_REMAP_ROW = 4096


@dataclass(frozen=True, eq=False)
class Texture:
    """A periodic albedo texture and its mip pyramid."""

    levels: tuple[NDArray[np.uint8], ...]
    """Level 0 .. L: (H / 2^l, W / 2^l, 3) BGR uint8 albedo."""
    texel_m: float
    """Size of a level-0 texel on the surface, in metres."""

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.levels[0].shape[:2]
        return h, w

    @property
    def period_m(self) -> tuple[float, float]:
        """(u, v) period of the pattern in metres."""
        h, w = self.shape
        return w * self.texel_m, h * self.texel_m

    def sample(
        self,
        u_m: NDArray[np.float32],
        v_m: NDArray[np.float32],
        footprint_m: NDArray[np.float32] | float,
    ) -> NDArray[np.float32]:
        """Albedo in [0, 1] at surface coordinates (u, v) (metres), trilinearly filtered for a
        pixel footprint of ``footprint_m`` metres. Returns (N, 3) float32 BGR."""
        u = np.asarray(u_m, np.float32).ravel()
        v = np.asarray(v_m, np.float32).ravel()
        n = u.size
        out = np.zeros((n, 3), np.float32)
        if n == 0:
            return out
        fp = np.broadcast_to(np.asarray(footprint_m, np.float32), u.shape).ravel()
        top = len(self.levels) - 1
        with np.errstate(divide="ignore"):
            level = np.clip(np.log2(np.maximum(fp, 1e-9) / self.texel_m), 0.0, float(top))
        base = np.minimum(level.astype(np.int32), max(top - 1, 0))
        frac = np.clip(level - base, 0.0, 1.0) if top > 0 else np.zeros_like(level)
        s = u / self.texel_m
        t = v / self.texel_m
        for lv in np.unique(base):
            idx = np.flatnonzero(base == lv)
            lo = _remap_points(self.levels[lv], s[idx], t[idx], int(lv))
            if top > 0:
                hi = _remap_points(self.levels[lv + 1], s[idx], t[idx], int(lv) + 1)
                w = frac[idx, None]
                out[idx] = lo * (1.0 - w) + hi * w
            else:
                out[idx] = lo
        out *= np.float32(1.0 / 255.0)
        return out


def _remap_points(
    image: NDArray[np.uint8], s: NDArray[np.float32], t: NDArray[np.float32], level: int
) -> NDArray[np.float32]:
    """Bilinear lookup of level-0 texel coordinates (s, t) in the level ``level`` image."""
    n = s.size
    rows = max(1, math.ceil(n / _REMAP_ROW))
    width = min(n, _REMAP_ROW)
    scale = np.float32(1.0 / (1 << level))
    mx = np.zeros(rows * width, np.float32)
    my = np.zeros(rows * width, np.float32)
    np.multiply(s, scale, out=mx[:n])
    np.multiply(t, scale, out=my[:n])
    mx[:n] -= np.float32(0.5)
    my[:n] -= np.float32(0.5)
    res = cv2.remap(
        image,
        mx.reshape(rows, width),
        my.reshape(rows, width),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_WRAP,
    )
    return res.reshape(-1, 3)[:n].astype(np.float32)


def build_texture(image: NDArray[np.uint8], texel_m: float) -> Texture:
    """Wrap a periodic BGR image (sides divisible by 2^levels) with its mip pyramid."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"texture image must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
    if not texel_m > 0:
        raise ValueError(f"texel_m must be positive, got {texel_m}")
    levels = [np.ascontiguousarray(image)]
    while len(levels) <= MAX_LEVELS:
        h, w = levels[-1].shape[:2]
        if h % 2 or w % 2 or min(h, w) < 8:
            break
        # A 2x2 box average of a periodic image is itself periodic (no border handling).
        half = cv2.resize(levels[-1], (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        levels.append(np.asarray(half, dtype=np.uint8))
    return Texture(levels=tuple(levels), texel_m=float(texel_m))


# --------------------------------------------------------------------------------- generators
def periodic_noise(
    rng: np.random.Generator, shape: tuple[int, int], beta: float = 2.0, cutoff: float = 2.0
) -> NDArray[np.float32]:
    """Tileable fractal noise with a 1/f^beta power spectrum, zero mean and unit std.

    ``cutoff`` (in cycles per texture) damps the lowest frequencies so that the texture has no
    single dominant blob.
    """
    h, w = shape
    white = rng.standard_normal((h, w)).astype(np.float32)
    spec = np.fft.rfft2(white)
    fy = np.fft.fftfreq(h)[:, None] * h
    fx = np.fft.rfftfreq(w)[None, :] * w
    f2 = fx * fx + fy * fy
    filt = (f2 + cutoff * cutoff) ** (-beta / 4.0)
    filt[0, 0] = 0.0
    field = np.fft.irfft2(spec * filt, s=(h, w)).astype(np.float32)
    field -= field.mean()
    std = float(field.std())
    return field / std if std > 0 else field


def octave_noise(
    rng: np.random.Generator, shape: tuple[int, int], band_px: float
) -> NDArray[np.float32]:
    """Tileable band-limited noise with features about ``band_px`` texels wide (unit std)."""
    h, w = shape
    white = rng.standard_normal((h, w)).astype(np.float32)
    spec = np.fft.rfft2(white)
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.sqrt(fx * fx + fy * fy) * band_px
    filt = np.exp(-0.5 * ((f - 1.0) / 0.6) ** 2)
    field = np.fft.irfft2(spec * filt, s=(h, w)).astype(np.float32)
    field -= field.mean()
    std = float(field.std())
    return field / std if std > 0 else field


def _palette(values: NDArray[np.float32], colors: NDArray[np.float32]) -> NDArray[np.float32]:
    """Map values in [0, 1] through a piecewise-linear colour ramp (K, 3) -> (H, W, 3)."""
    k = len(colors)
    x = np.clip(values, 0.0, 1.0) * (k - 1)
    i0 = np.minimum(x.astype(np.int32), k - 2)
    w = (x - i0)[..., None]
    return colors[i0] * (1 - w) + colors[i0 + 1] * w


def _to_unit(field: NDArray[np.float32], contrast: float = 0.18) -> NDArray[np.float32]:
    return np.clip(0.5 + contrast * field, 0.0, 1.0)


def _finish(img: NDArray[np.float32]) -> NDArray[np.uint8]:
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def random_color(
    rng: np.random.Generator, lo: float = 0.15, hi: float = 0.85
) -> NDArray[np.float32]:
    """A random BGR albedo with each channel in [lo, hi]."""
    return rng.uniform(lo, hi, 3).astype(np.float32)


def stone_texture(rng: np.random.Generator, shape: tuple[int, int]) -> NDArray[np.uint8]:
    """Multi-scale noise through a 3-colour ramp plus fine grain (concrete, stone, carpet)."""
    base = random_color(rng, 0.25, 0.75)
    colors = np.stack(
        [base * rng.uniform(0.45, 0.7), base, np.clip(base * rng.uniform(1.2, 1.5), 0, 1)]
    )
    field = periodic_noise(rng, shape, beta=rng.uniform(1.6, 2.2))
    fine = octave_noise(rng, shape, band_px=rng.uniform(3.0, 6.0))
    img = _palette(_to_unit(field, 0.22), colors)
    img *= (1.0 + 0.08 * fine)[..., None]
    return _finish(img)


def plank_texture(rng: np.random.Generator, shape: tuple[int, int]) -> NDArray[np.uint8]:
    """Wooden planks along u: per-plank tint, grain lines bent by noise, dark joints."""
    h, w = shape
    num_planks = int(rng.integers(4, 9))
    plank_h = h / num_planks
    y = np.arange(h, dtype=np.float32)[:, None]
    x = np.arange(w, dtype=np.float32)[None, :]
    warp = periodic_noise(rng, shape, beta=2.5) * 6.0
    wood = np.array(rng.choice([[0.22, 0.38, 0.55], [0.3, 0.45, 0.62], [0.18, 0.28, 0.42]]))
    wood = wood.astype(np.float32)
    plank = np.floor(y / plank_h).astype(np.int32) % num_planks
    tint = rng.uniform(0.8, 1.15, num_planks).astype(np.float32)[plank]
    grain_freq = 2 * np.pi * rng.uniform(3.0, 6.0) / plank_h
    grain = 0.5 + 0.5 * np.sin((y + warp) * grain_freq + plank * 1.7)
    fine = octave_noise(rng, shape, band_px=3.0)
    shade = tint * (0.82 + 0.18 * grain + 0.05 * fine)
    # Staggered butt joints: each plank row has its own joint position (periodic in x).
    joint_x = rng.uniform(0, w, num_planks).astype(np.float32)[plank]
    dxj = np.abs(((x - joint_x + w / 2) % w) - w / 2)
    dyj = np.abs(((y + plank_h / 2) % plank_h) - plank_h / 2)
    edge = (dyj > plank_h / 2 - 1.5) | (dxj < 1.5)
    shade = np.where(edge, shade * 0.45, shade)
    return _finish(wood[None, None, :] * shade[..., None] * 1.2)


def tile_texture(
    rng: np.random.Generator, shape: tuple[int, int], bricks: bool = False
) -> NDArray[np.uint8]:
    """Tiles or bricks: per-tile colour variation, dark grout lines, surface noise."""
    h, w = shape
    rows = int(rng.integers(4, 9)) * (2 if bricks else 1)
    cols = int(rng.integers(3, 6)) if bricks else rows * w // h
    cols = max(cols, 1)
    th, tw = h / rows, w / cols
    y = np.arange(h, dtype=np.float32)[:, None] * np.ones((1, w), np.float32)
    x = np.arange(w, dtype=np.float32)[None, :] * np.ones((h, 1), np.float32)
    row = np.floor(y / th).astype(np.int32)
    xs = (x + (row % 2) * (tw / 2 if bricks else 0.0)) % w
    col = np.floor(xs / tw).astype(np.int32)
    ids = row * cols + col
    base = np.array([0.22, 0.3, 0.62], np.float32) if bricks else random_color(rng, 0.35, 0.85)
    per_tile = rng.uniform(0.75, 1.2, (rows * cols, 3)).astype(np.float32)
    img = base[None, None] * per_tile[ids]
    img *= (1.0 + 0.1 * octave_noise(rng, shape, band_px=4.0))[..., None]
    img *= (1.0 + 0.06 * periodic_noise(rng, shape))[..., None]
    gx = np.minimum(xs % tw, tw - xs % tw)
    gy = np.minimum(y % th, th - y % th)
    grout = (gx < 1.5) | (gy < 1.5)
    img[grout] = np.float32(0.55) * img[grout].mean(axis=1, keepdims=True) + 0.12
    return _finish(img)


def poster_texture(rng: np.random.Generator, shape: tuple[int, int]) -> NDArray[np.uint8]:
    """A painted surface covered with posters: shapes, stripes and text (strong features)."""
    h, w = shape
    bg = stone_texture(rng, shape).astype(np.float32) / 255.0
    canvas = np.clip(0.35 * bg + 0.65 * random_color(rng, 0.5, 0.85)[None, None], 0, 1)
    img = _finish(canvas)
    num = int(rng.integers(6, 12)) * max(1, (h * w) // (512 * 512))
    for _ in range(num):
        ph, pw = int(rng.uniform(0.12, 0.3) * h), int(rng.uniform(0.08, 0.2) * w)
        ph, pw = max(ph, 24), max(pw, 24)
        y0, x0 = int(rng.integers(0, h)), int(rng.integers(0, w))
        poster = np.empty((ph, pw, 3), np.uint8)
        poster[:] = (random_color(rng, 0.3, 0.95) * 255).astype(np.uint8)
        for _ in range(int(rng.integers(4, 10))):
            color = tuple(int(c) for c in rng.integers(0, 256, 3))
            kind = rng.integers(0, 4)
            cx, cy = int(rng.integers(0, pw)), int(rng.integers(0, ph))
            size = int(rng.integers(4, max(5, min(ph, pw) // 2)))
            if kind == 0:
                cv2.circle(poster, (cx, cy), size, color, -1, cv2.LINE_AA)
            elif kind == 1:
                cv2.rectangle(poster, (cx, cy), (cx + size, cy + size // 2), color, -1)
            elif kind == 2:
                cv2.line(
                    poster,
                    (cx, cy),
                    (int(rng.integers(0, pw)), int(rng.integers(0, ph))),
                    color,
                    int(rng.integers(1, 4)),
                    cv2.LINE_AA,
                )
            else:
                text = "".join(rng.choice(list("ABCDEFGHKMNPRSTWXYZ0123456789"), 4))
                cv2.putText(
                    poster,
                    text,
                    (cx % max(1, pw - 20), cy),
                    cv2.FONT_HERSHEY_SIMPLEX,
                    rng.uniform(0.4, 1.2),
                    color,
                    int(rng.integers(1, 3)),
                    cv2.LINE_AA,
                )
        cv2.rectangle(poster, (0, 0), (pw - 1, ph - 1), (30, 30, 30), 1)
        _paste_wrapped(img, poster, y0, x0)
    return img


def _paste_wrapped(img: NDArray[np.uint8], patch: NDArray[np.uint8], y0: int, x0: int) -> None:
    """Paste ``patch`` at (y0, x0) into ``img``, wrapping around its borders (periodic)."""
    h, w = img.shape[:2]
    ph, pw = patch.shape[:2]
    ys = (np.arange(ph) + y0) % h
    xs = (np.arange(pw) + x0) % w
    img[np.ix_(ys, xs)] = patch


def fabric_texture(rng: np.random.Generator, shape: tuple[int, int]) -> NDArray[np.uint8]:
    """Clothing: stripes, checks or a printed pattern over a woven grain."""
    h, w = shape
    c1, c2 = random_color(rng, 0.1, 0.9), random_color(rng, 0.1, 0.9)
    y = np.arange(h, dtype=np.float32)[:, None]
    x = np.arange(w, dtype=np.float32)[None, :]
    kind = int(rng.integers(0, 3))
    if kind == 0:  # stripes (integer count across the period keeps it tileable)
        k = int(rng.integers(3, 9))
        m = (np.sin(2 * np.pi * k * y / h) > 0).astype(np.float32) * np.ones_like(x)
    elif kind == 1:  # plaid
        kx, ky = int(rng.integers(2, 6)), int(rng.integers(2, 6))
        m = 0.5 * (np.sin(2 * np.pi * kx * x / w) > 0.3) + 0.5 * (
            np.sin(2 * np.pi * ky * y / h) > 0.3
        )
    else:  # camouflage-like blobs
        m = (periodic_noise(rng, shape, beta=3.0, cutoff=3.0) > 0).astype(np.float32)
    img = c1[None, None] * (1 - m[..., None]) + c2[None, None] * m[..., None]
    img *= (1.0 + 0.12 * octave_noise(rng, shape, band_px=3.0))[..., None]
    img *= (1.0 + 0.1 * periodic_noise(rng, shape, beta=1.5))[..., None]
    return _finish(img)


def paint_texture(
    rng: np.random.Generator, shape: tuple[int, int], amplitude: float = 0.015
) -> NDArray[np.uint8]:
    """Weakly textured paint or skin: one colour with very faint low-frequency variation."""
    base = random_color(rng, 0.45, 0.9)
    field = periodic_noise(rng, shape, beta=2.5)
    img = base[None, None] * (1.0 + amplitude * field)[..., None]
    return _finish(img)


def skin_texture(rng: np.random.Generator, shape: tuple[int, int]) -> NDArray[np.uint8]:
    """Skin tone with faint blotches (weakly textured, as real skin is to stereo)."""
    tones = np.array(
        [[0.55, 0.66, 0.86], [0.42, 0.55, 0.75], [0.3, 0.4, 0.58], [0.2, 0.28, 0.42]], np.float32
    )
    base = tones[int(rng.integers(0, len(tones)))]
    field = periodic_noise(rng, shape, beta=2.0)
    img = base[None, None] * (1.0 + 0.04 * field)[..., None]
    return _finish(img)


def hair_texture(rng: np.random.Generator, shape: tuple[int, int]) -> NDArray[np.uint8]:
    """Dark, finely streaked hair."""
    base = np.array(rng.choice([[0.05, 0.07, 0.1], [0.1, 0.18, 0.3], [0.3, 0.5, 0.65]]))
    streak = octave_noise(rng, shape, band_px=2.5)
    img = base.astype(np.float32)[None, None] * (1.0 + 0.35 * streak)[..., None]
    return _finish(img)


GENERATORS = {
    "stone": stone_texture,
    "planks": plank_texture,
    "tiles": tile_texture,
    "bricks": lambda rng, shape: tile_texture(rng, shape, bricks=True),
    "posters": poster_texture,
    "fabric": fabric_texture,
    "paint": paint_texture,
    "skin": skin_texture,
    "hair": hair_texture,
}
"""Texture kinds by name: ``kind -> generator(rng, (h, w)) -> (h, w, 3) uint8``."""


def make_texture(
    kind: str, seed: int | tuple[int, ...], shape: tuple[int, int], texel_m: float
) -> Texture:
    """Generate a texture of ``kind`` (see ``GENERATORS``), deterministic from ``seed``."""
    if kind not in GENERATORS:
        raise ValueError(f"unknown texture kind {kind!r}; choose from {sorted(GENERATORS)}")
    rng = np.random.default_rng(seed)
    return build_texture(GENERATORS[kind](rng, shape), texel_m)
