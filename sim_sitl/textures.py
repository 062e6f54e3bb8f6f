"""Procedural textures (pure numpy) so photometric odometry finds gradients on every surface."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

TEXTURES = ("carpet", "wood", "concrete", "noise", "checker", "plain")


def _blurred_noise(rng: np.random.Generator, size: int, cells: int) -> NDArray[np.float64]:
    """Value noise: a ``cells`` x ``cells`` random grid bilinearly upsampled to ``size``."""
    grid = rng.random((cells + 1, cells + 1))
    x = np.linspace(0.0, cells, size, endpoint=False)
    i = x.astype(int)
    f = x - i
    g00 = grid[np.ix_(i, i)]
    g01 = grid[np.ix_(i, i + 1)]
    g10 = grid[np.ix_(i + 1, i)]
    g11 = grid[np.ix_(i + 1, i + 1)]
    fy, fx = f[:, None], f[None, :]
    return (g00 * (1 - fy) * (1 - fx) + g01 * (1 - fy) * fx + g10 * fy * (1 - fx) + g11 * fy * fx)


def make_texture(kind: str, rng: np.random.Generator, color: tuple[float, float, float] = (0.7, 0.7, 0.7),
                 size: int = 256) -> NDArray[np.uint8]:
    """An RGB8 ``size`` x ``size`` texture of the given kind, tinted by ``color``."""
    tint = np.asarray(color, dtype=float)[None, None, :]
    if kind == "carpet":  # multi-scale blobs plus fibre-level grain
        v = 0.5 * _blurred_noise(rng, size, 8) + 0.3 * _blurred_noise(rng, size, 32) + 0.2 * rng.random((size, size))
        img = tint * (0.45 + 0.8 * v[..., None])
    elif kind == "wood":
        y = np.linspace(0, 1, size)[:, None]
        rings = np.sin(2 * np.pi * (18 * y + 3 * _blurred_noise(rng, size, 6)))
        v = 0.6 + 0.25 * rings + 0.15 * _blurred_noise(rng, size, 64)
        img = tint * v[..., None]
    elif kind == "concrete":
        v = 0.55 + 0.25 * _blurred_noise(rng, size, 16) + 0.2 * _blurred_noise(rng, size, 64)
        img = tint * v[..., None]
    elif kind == "noise":
        v = 0.4 * _blurred_noise(rng, size, 12) + 0.4 * _blurred_noise(rng, size, 48) + 0.2
        img = tint * (0.4 + v[..., None]) * (0.85 + 0.3 * rng.random((1, 1, 3)))
    elif kind == "checker":
        ij = np.arange(size) // (size // 8)
        v = 0.35 + 0.5 * ((ij[:, None] + ij[None, :]) % 2) + 0.15 * _blurred_noise(rng, size, 32)
        img = tint * v[..., None]
    elif kind == "plain":
        v = 0.9 + 0.1 * _blurred_noise(rng, size, 8)
        img = tint * v[..., None]
    else:
        raise ValueError(f"unknown texture {kind!r} (known: {', '.join(TEXTURES)})")
    return np.clip(img * 255.0, 0, 255).astype(np.uint8)
