"""A tiny PNG encoder for heat maps (pure numpy + zlib; no plotting dependency).

``heatmap_png(values)`` returns the bytes of an 8-bit RGB PNG (PNG spec, ISO/IEC
15948: signature, IHDR, one IDAT of filter-0 scanlines, IEND).  NaN cells are grey.
"""
from __future__ import annotations

import struct
import zlib

import numpy as np

# a perceptually ordered dark-blue -> yellow ramp (viridis-like anchor colours)
_ANCHORS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98],
                     [253, 231, 37]], float)


def colourise(values: np.ndarray, vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """Map a 2-D array to RGB uint8 (rows top to bottom)."""
    v = np.asarray(values, float)
    finite = np.isfinite(v)
    lo = np.nanmin(v[finite]) if vmin is None and finite.any() else (vmin or 0.0)
    hi = np.nanmax(v[finite]) if vmax is None and finite.any() else (vmax or 1.0)
    x = np.clip((v - lo) / ((hi - lo) or 1.0), 0, 1)
    x = np.where(finite, x, 0.0) * (len(_ANCHORS) - 1)
    i = np.minimum(x.astype(int), len(_ANCHORS) - 2)
    f = (x - i)[..., None]
    rgb = _ANCHORS[i] * (1 - f) + _ANCHORS[i + 1] * f
    rgb[~finite] = 128
    return rgb.astype(np.uint8)


def encode_png(rgb: np.ndarray) -> bytes:
    """Bytes of an RGB PNG for a (height, width, 3) uint8 array."""
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[r].tobytes() for r in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + tag + data
                + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def heatmap_png(values: np.ndarray, scale: int = 8, vmin=None, vmax=None,
                flip_rows: bool = True) -> bytes:
    """PNG bytes of a heat map, each cell ``scale`` pixels (row 0 at the bottom)."""
    rgb = colourise(values, vmin, vmax)
    if flip_rows:
        rgb = rgb[::-1]
    rgb = np.repeat(np.repeat(rgb, scale, axis=0), scale, axis=1)
    return encode_png(np.ascontiguousarray(rgb))
