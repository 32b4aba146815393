"""Seeded 3D gradient (Perlin) noise and its fractal sum, vectorised in NumPy."""

from __future__ import annotations

import numpy as np

_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def perlin(points: np.ndarray, seed: int) -> np.ndarray:
    """Gradient noise in about [-1, 1] at ``points`` (N, 3); lattice period 256."""
    rng = np.random.default_rng(seed)
    perm = np.concatenate([rng.permutation(256)] * 2)
    grads = rng.normal(size=(256, 3))
    grads /= np.linalg.norm(grads, axis=1, keepdims=True)
    cell = np.floor(points).astype(np.int64)
    frac = points - cell
    fade = frac**3 * (frac * (frac * 6 - 15) + 10)
    cell &= 255
    out = np.zeros(len(points))
    for corner in _CORNERS:
        c = cell + corner
        h = perm[perm[perm[c[:, 0]] + c[:, 1]] + c[:, 2]]
        dot = np.einsum("ij,ij->i", grads[h], frac - corner)
        w = np.prod(np.where(corner == 1, fade, 1 - fade), axis=1)
        out += w * dot
    return out * np.sqrt(3.0)  # rescaled: values span about [-1, 1]


def fbm(points: np.ndarray, seed: int, octaves: int = 4, gain: float = 0.5) -> np.ndarray:
    """Fractal Brownian motion: octaves of :func:`perlin` at doubling frequency."""
    total, norm, amp = np.zeros(len(points)), 0.0, 1.0
    for o in range(octaves):
        total += amp * perlin(points * 2.0**o + 17.31 * o, seed + o)
        norm += amp
        amp *= gain
    return total / norm
