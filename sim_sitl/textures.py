"""Procedural textures (pure numpy) so photometric odometry finds gradients on every surface."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

TEXTURES = ("carpet", "wood", "concrete", "noise", "checker", "plain")


def _blurred_noise(rng: np.random.Generator, size: int, cells: int) -> NDArray[np.float32]:
    """Value noise: a ``cells`` x ``cells`` random grid bilinearly upsampled to ``size`` x ``size``."""
    grid = rng.random((cells + 1, cells + 1), dtype=np.float32)
    return np.asarray(cv2.resize(grid, (size, size), interpolation=cv2.INTER_LINEAR), dtype=np.float32)


def make_texture(kind: str, rng: np.random.Generator, color: tuple[float, float, float] = (0.7, 0.7, 0.7),
                 size: int = 256) -> NDArray[np.uint8]:
    """An RGB8 ``size`` x ``size`` texture of the given kind, tinted by ``color``."""
    tint = np.asarray(color, dtype=float)[None, None, :]
    k = max(1, size // 256)  # feature counts scale with the size: large surfaces keep fine detail
    if kind == "carpet":  # multi-scale blobs plus fibre-level grain
        grain = rng.random((size, size), dtype=np.float32)
        v = 0.5 * _blurred_noise(rng, size, 8 * k) + 0.3 * _blurred_noise(rng, size, 32 * k) + 0.2 * grain
        img = tint * (0.45 + 0.8 * v[..., None])
    elif kind == "wood":
        y = np.linspace(0, 1, size)[:, None]
        rings = np.sin(2 * np.pi * (18 * k * y + 3 * _blurred_noise(rng, size, 6 * k)))
        v = 0.6 + 0.25 * rings + 0.15 * _blurred_noise(rng, size, 64 * k)
        img = tint * v[..., None]
    elif kind == "concrete":
        v = 0.55 + 0.25 * _blurred_noise(rng, size, 16 * k) + 0.2 * _blurred_noise(rng, size, 64 * k)
        img = tint * v[..., None]
    elif kind == "noise":
        v = 0.4 * _blurred_noise(rng, size, 12 * k) + 0.4 * _blurred_noise(rng, size, 48 * k) + 0.2
        img = tint * (0.4 + v[..., None]) * (0.85 + 0.3 * rng.random((1, 1, 3)))
    elif kind == "checker":
        ij = np.arange(size) // (size // (8 * k))
        v = 0.35 + 0.5 * ((ij[:, None] + ij[None, :]) % 2) + 0.15 * _blurred_noise(rng, size, 32 * k)
        img = tint * v[..., None]
    elif kind == "plain":
        v = 0.9 + 0.1 * _blurred_noise(rng, size, 8 * k)
        img = tint * v[..., None]
    else:
        raise ValueError(f"unknown texture {kind!r} (known: {', '.join(TEXTURES)})")
    return np.clip(img * 255.0, 0, 255).astype(np.uint8)
