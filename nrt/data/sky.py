"""Procedural HDR skies with a sun, as equirectangular maps in Mitsuba's convention.

Radiance model (linear RGB, arbitrary units): a blue-to-white gradient from zenith to
horizon, a darker ground below the horizon, a forward-scattering glow around the sun and
a sun disk with a softened edge (a few texels wide, so the map resolves it). The sun
disk carries most of the irradiance, as outdoors.
"""

from __future__ import annotations

import numpy as np

from nrt.physics.envmap import texel_directions


def draw_sky_params(seed: int) -> dict:
    """Sun direction, sizes and colours of sky ``seed`` (JSON-serialisable)."""
    rng = np.random.default_rng([7919, seed])
    elevation = np.deg2rad(rng.uniform(15.0, 70.0))
    azimuth = rng.uniform(0.0, 2 * np.pi)
    to_sun = [np.cos(elevation) * np.sin(azimuth), np.sin(elevation),
              -np.cos(elevation) * np.cos(azimuth)]
    return {
        "seed": seed,
        "sun_direction": [float(x) for x in to_sun],  # direction *towards* the sun
        "sun_radius_deg": float(rng.uniform(4.0, 6.0)),
        "sun_radiance": float(rng.uniform(100.0, 200.0)),
        "sun_color": [1.0, float(rng.uniform(0.85, 0.95)), float(rng.uniform(0.7, 0.85))],
        "zenith_color": [float(x) for x in rng.uniform([0.15, 0.3, 0.7], [0.3, 0.45, 0.9])],
        "horizon_color": [float(x) for x in rng.uniform([0.7, 0.75, 0.8], [0.9, 0.9, 1.0])],
        "ground_color": [float(x) for x in rng.uniform([0.12, 0.1, 0.08], [0.25, 0.2, 0.15])],
    }


def sky_radiance(d: np.ndarray, p: dict) -> np.ndarray:
    """Radiance (..., 3) seen looking along unit directions ``d`` (..., 3)."""
    up = d[..., 1:2]
    t = np.clip(up, 0.0, 1.0) ** 0.5
    sky = (1 - t) * np.asarray(p["horizon_color"]) + t * np.asarray(p["zenith_color"])
    ground = np.asarray(p["ground_color"]) * (0.6 + 0.4 * np.exp(up * 4))
    base = np.where(up >= 0, sky, ground)
    cos_sun = np.clip(d @ np.asarray(p["sun_direction"]), -1.0, 1.0)[..., None]
    angle = np.arccos(cos_sun)
    radius = np.deg2rad(p["sun_radius_deg"])
    glow = 0.6 * np.exp(-angle / 0.25) * np.asarray(p["sun_color"])
    edge = np.clip((radius - angle) / (0.35 * radius) + 0.5, 0.0, 1.0)
    sun = p["sun_radiance"] * edge * np.asarray(p["sun_color"])
    return base + glow + sun


def sky_map(p: dict) -> np.ndarray:
    """The equirectangular map (H, W, 3) float32 of sky parameters ``p``."""
    height, width = p["resolution"]
    d = texel_directions(height, width).numpy()
    return sky_radiance(d, p).astype(np.float32)


