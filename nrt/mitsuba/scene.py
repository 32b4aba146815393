"""Mitsuba scene descriptions of nrt scenes: medium, lights, sensor.

Only what a scene's effects call for is built: the ``isotropic`` phase for isotropic
scenes, Mitsuba's ``hg`` for one g, and the registered ``nrt_hg_grid`` plugin (reading g
from a grid) when g varies; a one-channel extinction grid when extinction is grey;
``max_depth = order + 1`` from the maximum scattering order (-1: unlimited). Property
grids are ``[z, y, x]`` arrays; ``mi`` is the module :func:`nrt.mitsuba.variant.select_variant`
returned.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from nrt.errors import NrtError
from nrt.physics.phase import shared_g

log = logging.getLogger(__name__)


def unit_cube_to_box(mi, bbox: np.ndarray):
    """Transform mapping [0, 1]^3 (volume texture space) onto the box."""
    lo, hi = np.asarray(bbox[0], float), np.asarray(bbox[1], float)
    return mi.ScalarTransform4f().translate(lo.tolist()).scale((hi - lo).tolist())


def mitsuba_properties(grids: dict, effects: dict) -> dict[str, np.ndarray]:
    """Mitsuba's parameters of property grids (``[z, y, x]`` arrays): ``sigma_t`` (one
    channel unless chromatic), ``albedo`` (3 channels), and for the phase ``g``: the grid
    (R, R, R, 1) when g varies, the sigma_s-weighted mean (a float) for one shared g.

    Grey extinction is one sigma_t channel with an RGB albedo (the scene spec, nrt's media
    and stage=dpt share this model); grids whose sigma_a + sigma_s differs between
    channels are not grey, and only channel 0's extinction is rendered (a warning says so)."""
    sigma_s = np.asarray(grids["sigma_s"], np.float32)
    sigma_t = np.asarray(grids["sigma_a"], np.float32) + sigma_s
    albedo = np.where(sigma_t > 0, sigma_s / np.maximum(sigma_t, 1e-30), 0.0).astype(np.float32)
    spread = float(np.ptp(sigma_t, -1).max()) if sigma_t.size else 0.0
    if not effects["chromatic"] and spread > 1e-4 * max(float(sigma_t.max()), 1e-30):
        log.warning("The scene's extinction is grey (effects.chromatic=false) but these grids' "
                    "sigma_a + sigma_s differ between R, G and B (by up to %.3g): Mitsuba "
                    "renders channel 0's sigma_t with each channel's albedo.", spread)
    out = {"sigma_t": sigma_t if effects["chromatic"] else sigma_t[..., :1], "albedo": albedo}
    g = np.asarray(grids["g"], np.float32)
    if effects["phase"] == "varying_hg":
        out["g"] = g[..., None]
    elif effects["phase"] == "hg":
        out["g"] = shared_g(torch.from_numpy(sigma_s), torch.from_numpy(g))
    return out


def medium_dict(mi, grids: dict, bbox, effects: dict) -> dict:
    """Mitsuba ``heterogeneous`` medium of property grids (``[z, y, x]`` arrays) filling
    the box ``bbox`` (2, 3), with the phase the scene's effects declare."""
    to_world = unit_cube_to_box(mi, np.asarray(bbox))
    props = mitsuba_properties(grids, effects)

    def grid(data: np.ndarray) -> dict:
        return {"type": "gridvolume", "grid": mi.VolumeGrid(np.ascontiguousarray(data)),
                "to_world": to_world}

    phase = effects["phase"]
    if phase == "isotropic":
        phase_dict = {"type": "isotropic"}
    elif phase == "hg":
        phase_dict = {"type": "hg", "g": props["g"]}
    else:
        phase_dict = {"type": "nrt_hg_grid", "g": grid(props["g"])}
    return {"type": "heterogeneous", "sigma_t": grid(props["sigma_t"]),
            "albedo": grid(props["albedo"]), "scale": 1.0, "phase": phase_dict}


def max_depth(order: int) -> int:
    """Mitsuba ``max_depth`` for a maximum scattering order (-1: unlimited)."""
    return -1 if order < 0 else order + 1


def scene_dict(mi, spec: dict, grids: dict | None, envmap: np.ndarray, width: int,
               height: int, fov_x_deg: float, spp: int,
               extra_lights: list[dict] | None = None, integrator: str = "volpath") -> dict:
    """A complete scene: envmap (unless all black), medium box (if ``grids``), the scene's
    point emitters and ``extra_lights`` (:func:`emitter_dict`), one sensor. ``spec`` needs
    only ``bbox`` and ``effects``; ``integrator`` is ``volpath``, or ``prbvolpath`` for
    differentiable rendering."""
    bbox = np.asarray(spec["bbox"], float)
    envmap = np.ascontiguousarray(envmap, dtype=np.float32)
    scene = {
        "type": "scene",
        "integrator": {"type": integrator,
                       "max_depth": max_depth(spec["effects"]["max_scattering_order"])},
        "sensor": {
            "type": "perspective", "fov": float(fov_x_deg), "fov_axis": "x",
            "near_clip": 1e-3, "far_clip": 1e4,
            "film": {"type": "hdrfilm", "width": int(width), "height": int(height),
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": int(spp)},
        },
    }
    if np.any(envmap > 0):
        # An all-black map is left out: Mitsuba's envmap cannot importance-sample a map
        # without energy, and next-event estimation from the medium or a surface then turns
        # pixels into NaN (seen with Mitsuba 3.9.1); without it, the sky is black as wanted.
        scene["environment"] = {"type": "envmap", "bitmap": mi.Bitmap(envmap)}
    if grids is not None:
        centre, half = (bbox[0] + bbox[1]) / 2, (bbox[1] - bbox[0]) / 2
        scene["medium_box"] = {
            "type": "cube",
            "to_world": mi.ScalarTransform4f().translate(centre.tolist()).scale(half.tolist()),
            "bsdf": {"type": "null"},
            "interior": medium_dict(mi, grids, bbox, spec["effects"]),
        }
    for i, e in enumerate(spec["effects"]["emitters"]):
        scene[f"point_light_{i}"] = emitter_dict(mi, {"type": "point", **e})
    for i, light in enumerate(extra_lights or []):
        scene[f"extra_light_{i}"] = emitter_dict(mi, light)
    return scene


LIGHT_TYPES = ("point", "spot")


def emitter_dict(mi, light: dict) -> dict:
    """A local Mitsuba emitter: ``{type: point, position, intensity}`` or ``{type: spot,
    position, target, intensity, cutoff_deg (20), beam_width_deg (0.75 cutoff)}``, with
    ``intensity`` RGB radiant intensity (W/sr per unit area of radiance)."""
    kind = light.get("type", "point")
    if kind not in LIGHT_TYPES:
        raise NrtError(f"Light {dict(light)}: type must be one of {list(LIGHT_TYPES)}, got "
                       f"'{kind}'.")
    missing = {"position", "intensity"} | ({"target"} if kind == "spot" else set())
    missing -= set(light)
    if missing:
        raise NrtError(f"Light {dict(light)} lacks {sorted(missing)}: a point light needs "
                       "position and intensity [r, g, b]; a spot also target [x, y, z].")
    intensity = {"type": "rgb", "value": [float(v) for v in light["intensity"]]}
    position = [float(v) for v in light["position"]]
    if kind == "point":
        return {"type": "point", "position": position, "intensity": intensity}
    cutoff = float(light.get("cutoff_deg", 20.0))
    target = [float(v) for v in light["target"]]
    axis = np.subtract(target, position)
    up = [0, 0, 1] if abs(axis[1]) > 0.99 * np.linalg.norm(axis) else [0, 1, 0]
    return {"type": "spot", "intensity": intensity, "cutoff_angle": cutoff,
            "beam_width": float(light.get("beam_width_deg", 0.75 * cutoff)),
            "to_world": mi.ScalarTransform4f().look_at(
                origin=position, target=target, up=up)}
