"""Render a scene spec into a dataset folder with Mitsuba ``volpath`` (cached by spec hash).

Layout of a dataset folder (see README, "Data format")::

    scene.json                 resolved spec, its hash, Mitsuba version/variant, timings
    transforms_train.json      cameras + frames (one frame = one view under one environment)
    transforms_test.json
    envmaps/<name>.exr         equirectangular environment maps (Mitsuba convention)
    images/<name>/<split>_<i>.exr   linear HDR renders, RGB float32
    ground_truth.npz           sigma_a, sigma_s (Nz,Ny,Nx,3), g (Nz,Ny,Nx), bbox (2,3)

A dataset is written to a temporary sibling folder and renamed into place when complete,
so an interrupted render never leaves a half dataset that looks finished.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from tqdm import tqdm

from nrt.cameras import Intrinsics, look_at, sphere_positions
from nrt.data.exr import read_exr, write_exr
from nrt.data.media import medium_grids
from nrt.data.sky import sky_map
from nrt.data.spec import resolve_scene, spec_hash
from nrt.errors import DatasetError, SceneError
from nrt.files import TEMP_MARK, writing
from nrt.mitsuba.render import ViewRenderer
from nrt.mitsuba.scene import scene_dict
from nrt.mitsuba.variant import select_variant

log = logging.getLogger(__name__)

SPLITS = ("train", "test")


def camera_rig(spec: dict) -> tuple[dict[str, np.ndarray], Intrinsics]:
    """OpenGL camera-to-world matrices per split (views on a sphere, looking at the box
    centre; test views spread evenly among them) and the shared intrinsics."""
    cams = spec["cameras"]
    bbox = np.asarray(spec["bbox"], float)
    centre = bbox.mean(0)
    if cams["radius"] <= np.linalg.norm(bbox[1] - centre):
        raise SceneError(f"Scene key 'scene.cameras.radius' = {cams['radius']} puts cameras "
                         "inside or on the medium box; use a radius larger than the box's "
                         f"half diagonal ({np.linalg.norm(bbox[1] - centre):.3f}).")
    n_train, n_test = cams["num_train"], cams["num_test"]
    pos = centre + sphere_positions(n_train + n_test, cams["radius"], cams["seed"])
    test = np.zeros(len(pos), bool)
    if n_test:
        test[np.round(np.linspace(0, len(pos) - 1, n_test)).astype(int)] = True
    c2w = np.stack([look_at(p, centre) for p in pos])
    intr = Intrinsics.from_fov_x(cams["width"], cams["height"], np.deg2rad(cams["fov_x_deg"]))
    return {"train": c2w[~test], "test": c2w[test]}, intr


def environment_map(env: Mapping) -> np.ndarray:
    """Radiance map (H, W, 3) of a resolved environment entry (procedural sky or file)."""
    return sky_map(env) if env["type"] == "sky" else read_exr(env["path"])


def dataset_folder(spec: dict, data_root: str | Path) -> Path:
    """Where the dataset of ``spec`` lives: ``<data_root>/<name>-<spec hash>``."""
    return Path(data_root) / f"{spec['name']}-{spec_hash(spec)}"


def _transforms(intr: Intrinsics, bbox: list, env_files: dict, frames: list) -> dict:
    return {
        "camera_angle_x": intr.camera_angle_x,
        "fl_x": intr.fx, "fl_y": intr.fy, "cx": intr.cx, "cy": intr.cy,
        "w": intr.width, "h": intr.height,
        "medium_bbox": bbox,
        "environments": env_files,
        "frames": frames,
    }


def render_dataset(spec: dict, out_dir: str | Path, variant: str = "auto",
                   progress: bool = True) -> Path:
    """Render every view of ``spec`` under each environment into ``out_dir`` (atomic)."""
    out_dir = Path(out_dir)
    rigs, intr = camera_rig(spec)  # validates the rig before any work or file is made
    mi = select_variant(variant)
    start = time.perf_counter()
    tmp = out_dir.with_name(f".{out_dir.name}{TEMP_MARK}{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        with writing(f"the dataset of scene '{spec['name']}' into", tmp,
                     left=f"nothing of it is kept, and the next nrt-data or nrt-train renders "
                          f"it again into '{out_dir}'"):
            n_images = _render_into(tmp, spec, rigs, intr, mi, progress)
            seconds = time.perf_counter() - start
            info = {"spec": spec, "spec_hash": spec_hash(spec),
                    "renderer": {"mitsuba": mi.__version__, "variant": mi.variant(),
                                 "seconds": round(seconds, 2), "images": n_images}}
            with open(tmp / "scene.json", "w") as f:  # written last: marks the folder complete
                json.dump(info, f, indent=1)
            _move_into_place(tmp, out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # still here only if failed or redundant
    log.info("Rendered %d images of '%s' in %.1f s with Mitsuba %s (%s) into %s",
             n_images, spec["name"], seconds, mi.__version__, mi.variant(), out_dir)
    return out_dir


def _render_into(tmp: Path, spec: dict, rigs: dict[str, np.ndarray], intr: Intrinsics, mi,
                 progress: bool) -> int:
    """Write ground truth, envmaps, images and transforms of ``spec`` into ``tmp``."""
    (tmp / "envmaps").mkdir(parents=True)
    grids = medium_grids(spec)
    np.savez_compressed(tmp / "ground_truth.npz", bbox=np.asarray(spec["bbox"], np.float32),
                        **grids)
    cams = spec["cameras"]
    env_files, frames = {}, {split: [] for split in SPLITS}
    n_images = sum(len(r) for r in rigs.values()) * len(spec["environments"])
    bar = tqdm(total=n_images, desc=f"rendering {spec['name']}", unit="img", disable=not progress)
    for env_idx, (name, env) in enumerate(spec["environments"].items()):
        radiance = environment_map(env)
        env_files[name] = f"envmaps/{name}.exr"
        write_exr(tmp / env_files[name], radiance)
        (tmp / "images" / name).mkdir(parents=True)
        renderer = ViewRenderer(mi, scene_dict(
            mi, spec, grids, radiance, cams["width"], cams["height"], cams["fov_x_deg"],
            spec["spp"]))
        for split_idx, split in enumerate(SPLITS):
            for i, c2w in enumerate(rigs[split]):
                seed = (env_idx * len(SPLITS) + split_idx) * 100_003 + i + \
                    spec.get("photo_seed", 0) * 10_000_019
                file_path = f"images/{name}/{split}_{i:03d}.exr"
                write_exr(tmp / file_path, renderer.render(c2w, spec["spp"], seed))
                frames[split].append({"file_path": file_path, "environment": name,
                                      "transform_matrix": c2w.tolist()})
                bar.update()
    bar.close()
    for split in SPLITS:
        with open(tmp / f"transforms_{split}.json", "w") as f:
            json.dump(_transforms(intr, spec["bbox"], env_files, frames[split]), f, indent=1)
    return n_images


def _move_into_place(tmp: Path, out_dir: Path) -> None:
    """Rename the finished ``tmp`` to ``out_dir``. A complete ``out_dir`` (a concurrent
    render of the same spec finished first) is kept; an incomplete one is replaced."""
    if (out_dir / "scene.json").is_file():
        return
    if out_dir.exists():
        log.warning("Replacing the incomplete dataset folder %s (it has no scene.json)", out_dir)
        shutil.rmtree(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.replace(tmp, out_dir)
    except OSError:
        if not (out_dir / "scene.json").is_file():  # else a concurrent render moved first
            raise


def is_rendered(spec: dict, data_root: str | Path) -> bool:
    """Whether the cache under ``data_root`` holds the complete dataset of ``spec``."""
    return (dataset_folder(spec, data_root) / "scene.json").is_file()


def ensure_rendered(spec: dict, data_root: str | Path, variant: str = "auto",
                    progress: bool = True) -> Path:
    """The dataset folder of a resolved ``spec`` in the cache under ``data_root`` (keyed by
    the spec's hash), rendering it first when missing."""
    folder = dataset_folder(spec, data_root)
    if is_rendered(spec, data_root):
        log.info("Dataset of '%s' is up to date: %s", spec["name"], folder)
        return folder
    return render_dataset(spec, folder, variant=variant, progress=progress)


def dataset_name(scene_cfg: Mapping, data_root: str | Path) -> str | None:
    """The name of the dataset folder :func:`ensure_dataset` gives ``scene_cfg``, without
    rendering: ``scene.path``'s own name, else the cache folder's ``<name>-<spec hash>``;
    None for a family of scenes."""
    if scene_cfg.get("family") is not None:
        return None
    if scene_cfg.get("path"):
        return Path(str(scene_cfg["path"])).expanduser().resolve().name
    return dataset_folder(resolve_scene(scene_cfg), data_root).name


def ensure_dataset(scene_cfg: Mapping, data_root: str | Path, variant: str = "auto",
                   progress: bool = True) -> Path:
    """The dataset folder of a scene config: ``scene.path`` as given, else the cached
    render of its resolved spec, rendering it first when missing. A family of scenes
    (``scene.family``) is no one dataset: :func:`nrt.data.family.ensure_family` renders it."""
    if scene_cfg.get("family") is not None:
        raise SceneError(
            f"Scene '{scene_cfg.get('name')}' is a family of scenes (scene.family), not one "
            "dataset. `nrt-data scene=<family>` renders its members and prints the family "
            "folder, whose family.json lists every member's dataset folder; use one member "
            "with scene.path=<member folder> scene.name=<member name>, or train the whole "
            "family with `nrt-train stage=ea mode=generative scene=<family>`.")
    if scene_cfg.get("path"):
        folder = Path(str(scene_cfg["path"])).expanduser()
        if not folder.is_dir():
            raise DatasetError(f"Scene key 'scene.path' = '{folder}' is not a dataset folder. "
                               "Point scene.path at an existing folder (docs/data_format.md) or "
                               "set scene.path=null to render the scene.")
        return folder
    return ensure_rendered(resolve_scene(scene_cfg), data_root, variant, progress)
