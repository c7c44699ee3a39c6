"""Deterministic hashed noise for procedural textures (arrays in, arrays out, float32 in [0, 1))."""

from __future__ import annotations

import numpy as np

_M1 = np.uint32(0x7FEB352D)
_M2 = np.uint32(0x846CA68B)
_PRIMES = (np.uint32(0x9E3779B1), np.uint32(0x85EBCA77), np.uint32(0xC2B2AE3D), np.uint32(0x27D4EB2F))


def _mix(h: np.ndarray) -> np.ndarray:
    h = h ^ (h >> np.uint32(16))
    h = h * _M1
    h = h ^ (h >> np.uint32(15))
    h = h * _M2
    return h ^ (h >> np.uint32(16))


def _u32(a) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype.kind == "f":
        return a.astype(np.int32).view(np.uint32)
    return a.astype(np.int64).astype(np.uint32)


def hash01(seed: int, *ints) -> np.ndarray:
    """Hash up to 4 integer(-valued) arrays (broadcast) with a seed to float32 in [0, 1)."""
    h = np.uint32((((seed & 0xFFFFFFFF) * 0xC2B2AE3D) + 0x165667B1) & 0xFFFFFFFF)
    for k, a in enumerate(ints):
        h = _mix(h ^ (_u32(a) * _PRIMES[k % 4])) if k else h ^ (_u32(a) * _PRIMES[0])
    if len(ints) == 1:
        h = _mix(h)
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def cell_noise(seed: int, x: np.ndarray, y: np.ndarray, scale: float) -> np.ndarray:
    """Piecewise-constant noise on a square grid of ``scale`` metres."""
    s = np.float32(1.0 / scale)
    return hash01(seed, np.floor(x * s), np.floor(y * s))


def value_noise(seed: int, x: np.ndarray, y: np.ndarray, scale: float) -> np.ndarray:
    """Smooth 2D value noise with feature size ``scale`` metres."""
    s = np.float32(1.0 / scale)
    fx = np.asarray(x, np.float32) * s
    fy = np.asarray(y, np.float32) * s
    ix = np.floor(fx)
    iy = np.floor(fy)
    tx = fx - ix
    ty = fy - iy
    tx = tx * tx * (3 - 2 * tx)
    ty = ty * ty * (3 - 2 * ty)
    a = hash01(seed, ix, iy)
    b = hash01(seed, ix + 1, iy)
    c = hash01(seed, ix, iy + 1)
    d = hash01(seed, ix + 1, iy + 1)
    return (a + (b - a) * tx) * (1 - ty) + (c + (d - c) * tx) * ty


def fbm(seed: int, x: np.ndarray, y: np.ndarray, scale: float, octaves: int = 2) -> np.ndarray:
    """Fractal sum of value noise, normalised to [0, 1)."""
    total = np.zeros(np.shape(x), np.float32)
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        total += np.float32(amp) * value_noise(seed + 101 * o, x, y, scale / (2 ** o))
        norm += amp
        amp *= 0.5
    return total / np.float32(norm)
