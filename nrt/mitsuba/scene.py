"""Mitsuba 3 for nrt: variant choice, the spatially varying HG plugin, scene building.

Only what a scene's effects call for is built: the ``isotropic`` phase for isotropic
scenes, Mitsuba's ``hg`` for one g, and the registered ``nrt_hg_grid`` plugin (reading g
from a grid) when g varies; a one-channel extinction grid when extinction is grey;
``max_depth = order + 1`` from the maximum scattering order (-1: unlimited).
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from nrt.cameras import opengl_to_mitsuba
from nrt.errors import NrtError

log = logging.getLogger(__name__)

_PROBE = (
    "import mitsuba as mi; mi.set_variant('{v}'); "
    "s = mi.load_dict({{'type': 'scene', 'integrator': {{'type': 'path'}}, "
    "'shape': {{'type': 'sphere'}}, "
    "'sensor': {{'type': 'perspective', "
    "'film': {{'type': 'hdrfilm', 'width': 4, 'height': 4}}}}}}); "
    "mi.render(s, spp=1)"
)
_chosen_variant: str | None = None


def _variant_works(variant: str) -> bool:
    """Render a 4x4 image with ``variant`` in a subprocess (a bad LLVM aborts the process)."""
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE.format(v=variant)],
                              capture_output=True, timeout=300)
    except subprocess.TimeoutExpired:
        return False
    return proc.returncode == 0


def _cuda_present() -> bool:
    try:
        import torch

        return torch.cuda.is_available()
    except Exception:  # torch without CUDA support, or no driver
        return False


def select_variant(preferred: str = "auto"):
    """Set and return the Mitsuba module on the fastest working RGB variant.

    ``preferred='auto'`` tries ``cuda_ad_rgb`` (when CUDA is present), then ``llvm_ad_rgb``
    (needs LLVM >= 16, e.g. ``apt-get install libllvm19``), then ``scalar_rgb``; the
    environment variable ``NRT_MITSUBA_VARIANT`` overrides it. The choice is logged.
    """
    global _chosen_variant
    import mitsuba as mi

    preferred = os.environ.get("NRT_MITSUBA_VARIANT", preferred)
    if _chosen_variant is None:
        if preferred != "auto":
            if preferred not in mi.variants():
                raise NrtError(f"Mitsuba variant '{preferred}' (render.variant or "
                               f"NRT_MITSUBA_VARIANT) is not one of {mi.variants()}.")
            candidates = [preferred]
        else:
            candidates = (["cuda_ad_rgb"] if _cuda_present() else []) + ["llvm_ad_rgb"]
        _chosen_variant = next((v for v in candidates if _variant_works(v)), None)
        if _chosen_variant is None:
            if preferred != "auto":
                raise NrtError(f"Mitsuba variant '{preferred}' fails to render here. For "
                               "llvm_ad_rgb install a newer LLVM (apt-get install libllvm19) "
                               "or set DRJIT_LIBLLVM_PATH; or use render.variant=auto.")
            log.warning("llvm_ad_rgb does not work here (LLVM >= 16 missing: apt-get install "
                        "libllvm19); falling back to the slow scalar_rgb variant.")
            _chosen_variant = "scalar_rgb"
        log.info("Mitsuba %s, variant %s", mi.__version__, _chosen_variant)
    mi.set_variant(_chosen_variant)
    _register_plugins(mi)
    return mi


def _register_plugins(mi) -> None:
    from nrt.data.phase_plugin import make_hg_grid_phase

    mi.register_phase("nrt_hg_grid", make_hg_grid_phase(mi))


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
        weight = sigma_s.mean(-1).astype(np.float64)
        out["g"] = float((weight * g).sum() / weight.sum()) if weight.sum() > 0 else float(g.mean())
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
               extra_lights: list[dict] | None = None) -> dict:
    """A complete scene: envmap (unless all black), medium box (if ``grids``), the scene's
    point emitters and ``extra_lights`` (:func:`emitter_dict`), one sensor. ``spec`` needs
    only ``bbox`` and ``effects``."""
    bbox = np.asarray(spec["bbox"], float)
    envmap = np.ascontiguousarray(envmap, dtype=np.float32)
    scene = {
        "type": "scene",
        "integrator": {"type": "volpath",
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


class ViewRenderer:
    """Renders one loaded scene from many OpenGL cameras, reusing the compiled kernel."""

    def __init__(self, mi, scene_description: dict):
        self.mi = mi
        self.scene = mi.load_dict(scene_description)
        self.params = mi.traverse(self.scene)
        self._key = next(k for k in self.params.keys() if k.endswith("to_world")
                         and k.startswith("sensor"))

    def set_camera(self, c2w: np.ndarray) -> None:
        """Place the sensor at the OpenGL camera-to-world ``c2w`` (4, 4)."""
        self.params[self._key] = self.mi.ScalarTransform4f(opengl_to_mitsuba(c2w).tolist())
        self.params.update()

    def render(self, c2w: np.ndarray, spp: int, seed: int) -> np.ndarray:
        """Linear RGB radiance (H, W, 3) float32 seen by camera ``c2w`` (OpenGL)."""
        self.set_camera(c2w)
        img = self.mi.render(self.scene, spp=int(spp), seed=int(seed))
        return np.asarray(img, dtype=np.float32)[..., :3]


def write_medium_files(mi, folder: str | Path, grids: dict, bbox, effects: dict) -> dict[str, str]:
    """Export property grids for Mitsuba: ``sigma_t.vol``, ``albedo.vol`` (and ``g.vol``
    when g varies) in Mitsuba's binary grid format, and ``medium.xml``, a scene holding the
    medium box (load it with ``mi.load_file`` or ``<include>`` it; a g grid needs the
    ``nrt_hg_grid`` plugin, registered by :func:`select_variant`)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    props = mitsuba_properties(grids, effects)
    files = {}
    for key, value in props.items():
        if isinstance(value, np.ndarray):
            files[key] = folder / f"{key}.vol"
            mi.VolumeGrid(np.ascontiguousarray(value, np.float32)).write(str(files[key]))
    lo, hi = (np.asarray(b, float) for b in np.asarray(bbox))
    box = (f'<transform name="to_world"><scale value="{_xyz(hi - lo)}"/>'
           f'<translate value="{_xyz(lo)}"/></transform>')
    cube = (f'<transform name="to_world"><scale value="{_xyz((hi - lo) / 2)}"/>'
            f'<translate value="{_xyz((hi + lo) / 2)}"/></transform>')

    def volume(name: str) -> str:
        return (f'<volume type="gridvolume" name="{name}"><string name="filename" '
                f'value="{files[name].name}"/>{box}</volume>')
    phase = effects["phase"]
    if phase == "isotropic":
        phase_xml = '<phase type="isotropic"/>'
    elif phase == "hg":
        phase_xml = f'<phase type="hg"><float name="g" value="{props["g"]:.6f}"/></phase>'
    else:
        phase_xml = f'<phase type="nrt_hg_grid">{volume("g")}</phase>'
    xml = (f'<scene version="3.0.0">\n  <!-- nrt export: medium box {lo.tolist()} .. '
           f'{hi.tolist()} -->\n  <shape type="cube" id="medium_box">\n    {cube}\n'
           '    <bsdf type="null"/>\n    <medium type="heterogeneous" name="interior">\n'
           f'      {volume("sigma_t")}\n      {volume("albedo")}\n'
           f'      <float name="scale" value="1"/>\n      {phase_xml}\n    </medium>\n'
           '  </shape>\n</scene>\n')
    files["xml"] = folder / "medium.xml"
    files["xml"].write_text(xml)
    return {k: str(v) for k, v in files.items()}


def _xyz(v) -> str:
    return ", ".join(f"{float(x):.9g}" for x in v)
