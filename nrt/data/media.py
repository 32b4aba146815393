"""Procedural heterogeneous media: noise-perturbed blobs combined into property grids.

Elements live in box-normalised coordinates (the medium box mapped to [-1, 1]^3). An
element's density ``d(x)`` in [0, 1] is a sphere of ``radius`` whose surface is displaced
by fractal noise; ``sharpness`` sets how fast density ramps up inside the surface, from
diffuse (1.5) to sharp-edged (12). It scales the element's RGB ``sigma_a`` and ``sigma_s``
(per unit length). Overlapping elements add their coefficients; the phase function at a
point is one Henyey-Greenstein lobe whose ``g`` is the sigma_s-weighted mean of the
elements' ``g`` (channel-mean sigma_s as weight), i.e. the mixture's mean cosine. A window
fades all density to zero in the outer 5% of the box, so nothing is cut by its faces: it
reaches zero at the outermost cell centres, because renderers interpolate the cell-centred
grid and clamp at the faces (Mitsuba's ``gridvolume``), i.e. the face takes the value of
the outermost cells.
"""

from __future__ import annotations

import numpy as np
import torch

from nrt.data.noise import fbm
from nrt.physics.volume import cell_centres

_G_WEIGHT_EPS = 1e-6
"""Keeps ``g`` defined (the plain mean of the elements' g) where no element scatters."""


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def box_window(p: np.ndarray, margin: float = 0.05, inset: float = 0.0) -> np.ndarray:
    """1 inside the box, falling smoothly to 0 at distance ``inset`` from its faces and
    staying 0 beyond (``p`` box-normalised, so the faces are at +-1)."""
    t = (1 - inset - np.abs(p)) / (2 * margin)
    return np.prod(_smoothstep(np.where(t < 1e-9, 0.0, t)), axis=-1)  # exact 0 despite rounding


def element_density(p: np.ndarray, element: dict) -> np.ndarray:
    """Density in [0, 1] of one element at box-normalised points ``p`` (N, 3)."""
    rot = np.asarray(element["rotation"], float)
    q = (p - np.asarray(element["center"], float)) @ rot / float(element["radius"])
    seed, octaves = int(element["noise_seed"]), int(element["octaves"])
    freq = float(element["frequency"])
    surface = 1 - np.linalg.norm(q, axis=-1) + float(element["amplitude"]) * fbm(
        q * freq, seed, octaves)
    detail = 0.75 + 0.25 * fbm(q * 2 * freq, seed + 1000, octaves)
    return np.clip(_smoothstep(surface * float(element["sharpness"])) * detail, 0.0, 1.0)


def medium_grids(spec: dict) -> dict[str, np.ndarray]:
    """Ground-truth grids of a resolved scene spec at cell centres, indexed ``[z, y, x]``.

    Returns ``sigma_a`` and ``sigma_s`` (R, R, R, 3) per unit length and ``g`` (R, R, R),
    all float32.
    """
    bbox = np.asarray(spec["bbox"], float)
    res = int(spec["medium"]["resolution"])
    world = cell_centres(res, torch.as_tensor(bbox)).numpy().reshape(-1, 3)
    p = 2 * (world - bbox[0]) / (bbox[1] - bbox[0]) - 1
    window = box_window(p, inset=1.0 / res)  # zero on the outermost cell centres
    sigma_a = np.zeros((len(p), 3))
    sigma_s = np.zeros((len(p), 3))
    g_num = np.zeros(len(p))
    g_den = np.zeros(len(p))
    for e in spec["medium"]["elements"]:
        d = element_density(p, e) * window
        s = np.asarray(e["sigma_s"], float)
        sigma_a += d[:, None] * np.asarray(e["sigma_a"], float)
        sigma_s += d[:, None] * s
        w = d * s.mean() + _G_WEIGHT_EPS
        g_num += w * float(e["g"])
        g_den += w
    shape = (res, res, res)
    return {
        "sigma_a": sigma_a.reshape(*shape, 3).astype(np.float32),
        "sigma_s": sigma_s.reshape(*shape, 3).astype(np.float32),
        "g": (g_num / g_den).reshape(shape).astype(np.float32),
    }
