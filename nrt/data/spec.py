"""Scene specifications: from a Hydra ``scene`` config to a fully resolved, hashable spec.

A scene config declares the medium box, procedural elements (drawn from a seed, or given
explicitly), environment maps, the camera rig, samples per pixel and the scene's
**effects**. :func:`resolve_scene` draws every random quantity once and returns a plain
dict that is written next to the dataset (``scene.json``); :func:`spec_hash` of that dict
names the dataset folder, so a changed spec renders anew and never overwrites.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from nrt.data.sky import draw_sky_params
from nrt.errors import SceneError
from nrt.files import check_name

FORMAT_VERSION = 2
"""Bumped whenever rendering or the dataset layout changes meaning (invalidates caches).
2: the medium's box window reaches zero on the outermost grid cells."""

PHASES = ("isotropic", "hg", "varying_hg")


def _require(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise SceneError(f"Scene key 'scene.{key}': {message}")


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random proper rotation matrix (3, 3)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _draw_element(rng: np.random.Generator, medium: Mapping, chromatic: bool, g: float) -> dict:
    """One procedural cloud element in box-normalised units (the box is [-1, 1]^3). Grey
    extinction (``chromatic=False``) is one sigma_t for R, G and B with an RGB albedo, the
    model Mitsuba renders (a one-channel sigma_t grid) and nrt's media learn."""
    sigma_t_max = float(medium["max_extinction"])
    scale = rng.uniform(0.5, 1.0) * sigma_t_max
    sigma_t = scale * (rng.uniform(0.4, 1.0, 3) if chromatic else np.ones(3))
    albedo = rng.uniform(*medium["albedo_range"], 3)
    return {
        "center": rng.uniform(-0.25, 0.25, 3).tolist(),
        "radius": float(rng.uniform(0.45, 0.7)),
        "rotation": random_rotation(rng).tolist(),
        "noise_seed": int(rng.integers(0, 2**31 - 1)),
        "frequency": float(rng.uniform(1.5, 4.0)),
        "amplitude": float(rng.uniform(0.2, 0.6)),
        "octaves": 4,
        # 1.5: soft, diffuse falloff ... 12: sharp-edged cumulus-like boundary
        "sharpness": float(rng.uniform(1.5, 12.0)),
        "sigma_a": ((1 - albedo) * sigma_t).tolist(),
        "sigma_s": (albedo * sigma_t).tolist(),
        "g": g,
    }


def _resolve_elements(scene: Mapping, rng: np.random.Generator) -> list[dict]:
    medium, effects = scene["medium"], scene["effects"]
    phase, chromatic = effects["phase"], bool(effects["chromatic"])
    g_lo, g_hi = medium["g_range"]
    _require(-0.95 <= g_lo <= g_hi <= 0.95, "medium.g_range", "needs -0.95 <= lo <= hi <= 0.95")
    shared_g = 0.0
    if phase == "hg":
        shared_g = float(medium["g"]) if medium.get("g") is not None else float(
            rng.uniform(g_lo, g_hi))
        _require(abs(shared_g) <= 0.95, "medium.g", f"|g| must be <= 0.95, got {shared_g}")
    if medium.get("elements"):
        elements = [dict(e) for e in medium["elements"]]
        for i, e in enumerate(elements):
            missing = {"center", "radius", "sigma_a", "sigma_s"} - set(e)
            _require(not missing, f"medium.elements[{i}]", f"missing {sorted(missing)}")
            _require(isinstance(e["radius"], int | float) and e["radius"] > 0,
                     f"medium.elements[{i}].radius", "must be one positive number (the "
                     "element's size; use rotation and noise for other shapes)")
            for key in ("center", "sigma_a", "sigma_s"):
                _require(np.shape(e[key]) == (3,), f"medium.elements[{i}].{key}",
                         "must be a list of 3 numbers")
            e.setdefault("rotation", np.eye(3).tolist())
            e.setdefault("noise_seed", i)
            e.setdefault("frequency", 2.0)
            e.setdefault("amplitude", 0.0)
            e.setdefault("octaves", 4)
            e.setdefault("sharpness", 4.0)
            e.setdefault("g", shared_g)
            if phase != "varying_hg":
                e["g"] = shared_g
            e = {k: (np.asarray(v).tolist() if isinstance(v, (list, tuple)) else v)
                 for k, v in e.items()}
            elements[i] = e
    else:
        n = int(medium["num_elements"])
        _require(1 <= n <= 4, "medium.num_elements", f"must be 1-4, got {n}")
        elements = []
        for _ in range(n):
            g = float(rng.uniform(g_lo, g_hi)) if phase == "varying_hg" else shared_g
            elements.append(_draw_element(rng, medium, chromatic, g))
    for i, e in enumerate(elements):
        if not chromatic:
            t = np.asarray(e["sigma_a"]) + np.asarray(e["sigma_s"])
            _require(np.allclose(t, t[0]), f"medium.elements[{i}]",
                     "effects.chromatic=false needs sigma_a + sigma_s equal in R, G, B "
                     "(one grey sigma_t; the albedo sigma_s / sigma_t may differ)")
        _require(min(e["sigma_a"]) >= 0 and min(e["sigma_s"]) >= 0, f"medium.elements[{i}]",
                 "sigma_a and sigma_s must be non-negative")
        if phase == "isotropic":
            e["g"] = 0.0
        _require(abs(e["g"]) <= 0.95, f"medium.elements[{i}].g", "|g| must be <= 0.95")
    return elements


def _resolve_environments(env: Mapping) -> dict[str, dict]:
    out: dict[str, dict] = {}
    height, width = (int(x) for x in env["resolution"])
    _require(height >= 3 and width >= 2 * (height - 1) - 1, "environments.resolution",
             f"needs [H, W] with H >= 3 and W about 2H, got {[height, width]}")
    for seed in env.get("sky_seeds") or []:
        out[f"sky{int(seed)}"] = {"type": "sky", "resolution": [height, width],
                                  **draw_sky_params(int(seed))}
    for name, path in (env.get("files") or {}).items():
        p = Path(str(path)).expanduser()
        _require(p.is_file(), f"environments.files.{name}", f"file '{p}' does not exist")
        digest = hashlib.sha1(p.read_bytes()).hexdigest()
        out[str(name)] = {"type": "file", "path": str(p.resolve()), "sha1": digest}
    _require(bool(out), "environments", "declare at least one sky seed or environment file")
    return out


def resolve_scene(scene: Mapping[str, Any]) -> dict:
    """Draw every random quantity of a scene config; the result is JSON-serialisable. The
    name, which names the dataset folder, must keep it inside the cache
    (:func:`nrt.files.check_name`)."""
    check_name("scene.name", scene["name"], SceneError)
    effects = scene["effects"]
    _require(effects["phase"] in PHASES, "effects.phase",
             f"must be one of {PHASES}, got '{effects['phase']}'")
    order = int(effects["max_scattering_order"])
    _require(order >= -1, "effects.max_scattering_order", "use -1 (all orders) or >= 0")
    bbox = np.asarray(scene["bbox"], dtype=float)
    _require(bbox.shape == (2, 3) and bool(np.all(bbox[1] > bbox[0])), "bbox",
             "must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min")
    emitters = [
        {"position": [float(x) for x in e["position"]],
         "intensity": [float(x) for x in e["intensity"]]}
        for e in (effects.get("emitters") or [])
    ]
    cams = scene["cameras"]
    _require(int(cams["num_train"]) >= 1 and int(cams["num_test"]) >= 0, "cameras",
             "needs num_train >= 1 and num_test >= 0")
    rng = np.random.default_rng(int(scene["seed"]))
    medium = scene["medium"]
    res = int(medium["resolution"])
    _require(res >= 2, "medium.resolution", f"must be >= 2, got {res}")
    photo_seed = int(scene.get("photo_seed") or 0)
    _require(photo_seed >= 0, "photo_seed", f"must be >= 0, got {photo_seed}")
    resolved = {
        "format_version": FORMAT_VERSION,
        "name": str(scene["name"]),
        "seed": int(scene["seed"]),
        "bbox": bbox.tolist(),
        "effects": {
            "phase": str(effects["phase"]),
            "chromatic": bool(effects["chromatic"]),
            "max_scattering_order": order,
            "emitters": emitters,
        },
        "medium": {"resolution": res, "elements": _resolve_elements(scene, rng)},
        "environments": _resolve_environments(scene["environments"]),
        "cameras": {
            "num_train": int(cams["num_train"]),
            "num_test": int(cams["num_test"]),
            "width": int(cams["width"]),
            "height": int(cams["height"]),
            "fov_x_deg": float(cams["fov_x_deg"]),
            "radius": float(cams["radius"]),
            "seed": int(cams["seed"]),
        },
        "spp": int(scene["spp"]),
    }
    if photo_seed:  # another Monte Carlo noise realisation of the same photos
        resolved["photo_seed"] = photo_seed
    return resolved


def spec_hash(spec: Mapping) -> str:
    """Short stable hash of a resolved spec (names the dataset folder)."""
    text = json.dumps(spec, sort_keys=True, separators=(",", ":"))
    return hashlib.sha1(text.encode()).hexdigest()[:10]
