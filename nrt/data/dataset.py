"""Load and validate a dataset folder (rendered by nrt or written by any other tool).

Every user mistake raises :class:`~nrt.errors.DatasetError` naming the file or key and
the fix. See docs/data_format.md for the layout; ``ground_truth.npz`` and ``scene.json``
are optional (metrics that need ground truth are then skipped).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from nrt.cameras import Intrinsics, pixel_rays
from nrt.data.exr import read_exr
from nrt.data.grids import PROPERTY_KEYS, load_property_grids
from nrt.errors import DatasetError
from nrt.physics.envmap import EnvironmentMap

log = logging.getLogger(__name__)

DEFAULT_BBOX = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
GROUND_TRUTH_FILE = "ground_truth.npz"


@dataclass
class SceneDataset:
    """One split of a dataset as tensors (CPU, float32).

    ``images`` (N, H, W, 3) linear radiance; ``c2w`` (N, 4, 4) OpenGL cameras;
    ``env_index`` (N,) index into ``env_names`` / ``envmaps``; ``bbox`` (2, 3) medium box;
    ``ground_truth``: ``sigma_a``, ``sigma_s`` (Nz, Ny, Nx, 3), ``g`` (Nz, Ny, Nx) or None.
    """

    root: Path
    split: str
    images: torch.Tensor
    c2w: torch.Tensor
    intrinsics: Intrinsics
    env_index: torch.Tensor
    env_names: list[str]
    envmaps: list[EnvironmentMap]
    bbox: torch.Tensor
    ground_truth: dict[str, torch.Tensor] | None
    spec: dict | None

    def __len__(self) -> int:
        return self.images.shape[0]

    def environments_used(self) -> list[str]:
        """Names of the environments lighting this split's frames."""
        return [self.env_names[i] for i in sorted(set(self.env_index.tolist()))]

    def select_environments(self, wanted: list[str | int]) -> SceneDataset:
        """The frames lit by the environments ``wanted`` (names, or positions in
        ``env_names``); environment indices keep their meaning."""
        keep = []
        for item in wanted:
            if isinstance(item, int) and 0 <= item < len(self.env_names):
                keep.append(item)
            elif str(item) in self.env_names:
                keep.append(self.env_names.index(str(item)))
            else:
                raise DatasetError(
                    f"Dataset '{self.root}': the stage trains on environment '{item}' "
                    f"(scene.environments.train, or stage.environments), but the dataset has "
                    f"environments {self.env_names}: give names or positions 0.."
                    f"{len(self.env_names) - 1}, e.g. scene.environments.train=[0], or null "
                    "for all.")
        mask = torch.isin(self.env_index, torch.tensor(keep))
        return replace(self, images=self.images[mask], c2w=self.c2w[mask],
                       env_index=self.env_index[mask])

    def rays(self, i: int, offsets: torch.Tensor | None = None):
        """Origins, unit view directions and pixel radiance of image ``i``, (H, W, 3) each."""
        o, d = pixel_rays(self.c2w[i], self.intrinsics, offsets)
        return o, d, self.images[i]


def _fail(path: Path, message: str) -> DatasetError:
    return DatasetError(f"Dataset file '{path}': {message}")


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise _fail(path, "not found. A dataset folder needs transforms_train.json and "
                          "transforms_test.json; render one with `nrt-data scene=...` or "
                          "point scene.path at a complete folder.")
    try:
        with open(path) as f:
            data = json.load(f)
    except json.JSONDecodeError as exc:
        raise _fail(path, f"is not valid JSON ({exc}). Fix or re-render it.") from exc
    if not isinstance(data, dict):
        raise _fail(path, "must hold a JSON object with 'frames'.")
    return data


def _number(meta: dict, key: str, path: Path, default: float | None = None) -> float:
    value = meta.get(key, default)
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if not math.isfinite(x):
        raise _fail(path, f"'{key}' must be a finite number, got {value!r}.")
    return x


def _intrinsics(meta: dict, path: Path, width: int, height: int) -> Intrinsics:
    w, h = _number(meta, "w", path, width), _number(meta, "h", path, height)
    if (w, h) != (width, height):
        raise _fail(path, f"declares images of {w:g}x{h:g} pixels ('w', 'h') but the images "
                          f"are {width}x{height}; fix 'w'/'h' or the images.")
    if "fl_x" in meta:
        fx = _number(meta, "fl_x", path)
        fy = _number(meta, "fl_y", path, fx)
        if fx <= 0 or fy <= 0:
            raise _fail(path, f"focal lengths 'fl_x' = {fx:g} and 'fl_y' = {fy:g} must be "
                              "positive (pixels).")
        return Intrinsics(width, height, fx, fy, _number(meta, "cx", path, width / 2),
                          _number(meta, "cy", path, height / 2))
    if "camera_angle_x" in meta:
        angle = _number(meta, "camera_angle_x", path)
        if not 0 < angle < math.pi:
            raise _fail(path, f"'camera_angle_x' = {angle:g} must be the horizontal field of "
                              "view in radians, between 0 and pi.")
        return Intrinsics.from_fov_x(width, height, angle)
    raise _fail(path, "has neither 'camera_angle_x' nor 'fl_x'; add the horizontal field of "
                      "view in radians ('camera_angle_x') or focal lengths in pixels.")


def _environments(meta: dict, path: Path, root: Path) -> tuple[list[str], list[EnvironmentMap]]:
    envs = meta.get("environments")
    if not isinstance(envs, dict) or not envs:
        raise _fail(path, "lacks 'environments', a mapping from environment name to its "
                          "equirectangular EXR (e.g. {\"sky0\": \"envmaps/sky0.exr\"}); the "
                          "known illumination is part of every nrt dataset.")
    names = list(envs)
    maps = []
    for name in names:
        file = root / str(envs[name])
        if not isinstance(envs[name], str) or not file.is_file():
            raise _fail(path, f"environments.{name} names the map {envs[name]!r}, but "
                              f"'{file}' does not exist; fix the entry (a path relative to the "
                              "dataset folder) or add the equirectangular EXR there.")
        radiance = torch.from_numpy(read_exr(file))
        try:
            maps.append(EnvironmentMap(radiance))
        except ValueError as exc:
            raise _fail(file, f"{exc}; it is environments.{name} of {path.name}.") from exc
    return names, maps


def _frame_matrix(frame: dict, k: int, path: Path) -> np.ndarray:
    try:
        m = np.asarray(frame.get("transform_matrix", []), dtype=float)
    except (TypeError, ValueError):
        m = np.full(0, np.nan)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise _fail(path, f"frames[{k}].transform_matrix must be a finite 4x4 matrix.")
    if not np.allclose(m[3], [0, 0, 0, 1]):
        raise _fail(path, f"frames[{k}].transform_matrix must end in the row [0, 0, 0, 1].")
    return m


def _ground_truth(root: Path) -> dict[str, torch.Tensor] | None:
    path = root / GROUND_TRUTH_FILE
    if not path.is_file():
        log.info("No %s in %s: metrics that need ground truth will be skipped.",
                 GROUND_TRUTH_FILE, root)
        return None
    grids = load_property_grids(path)
    return {k: grids[k] for k in PROPERTY_KEYS}


def load_dataset(root: str | Path, split: str = "train") -> SceneDataset:
    """Read one split of the dataset folder ``root`` into tensors, validating everything."""
    root = Path(root).expanduser()
    if not root.is_dir():
        raise DatasetError(f"Dataset folder '{root}' does not exist. Render it with "
                           "`nrt-data scene=<name>` or fix scene.path.")
    path = root / f"transforms_{split}.json"
    meta = _read_json(path)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise _fail(path, "has no 'frames' list (or it is empty).")
    env_names, envmaps = _environments(meta, path, root)
    try:
        bbox = np.asarray(meta.get("medium_bbox", DEFAULT_BBOX), dtype=float)
    except (TypeError, ValueError):
        bbox = np.full(0, np.nan)
    if bbox.shape != (2, 3) or not np.all(bbox[1] > bbox[0]):
        raise _fail(path, "'medium_bbox' must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] "
                          f"with max > min, got {meta.get('medium_bbox')!r}.")
    images, mats, env_index = [], [], []
    for k, frame in enumerate(frames):
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise _fail(path, f"frames[{k}] has no 'file_path'.")
        env = frame.get("environment", env_names[0] if len(env_names) == 1 else None)
        if env not in env_names:
            raise _fail(path, f"frames[{k}].environment is '{env}', which is not one of the "
                              f"declared environments {env_names}; add it to 'environments' "
                              "or fix the frame.")
        m = _frame_matrix(frame, k, path)
        inside = np.all(m[:3, 3] >= bbox[0]) and np.all(m[:3, 3] <= bbox[1])
        if inside:
            raise _fail(path, f"frames[{k}] places the camera at {m[:3, 3].tolist()}, inside the "
                              f"medium box {bbox.tolist()}; cameras must look at the medium "
                              "from outside (fix the pose or 'medium_bbox').")
        file = root / str(frame["file_path"])
        if file.suffix.lower() != ".exr":
            file = file.with_name(file.name + ".exr")
        if not file.is_file():
            raise _fail(path, f"frames[{k}].file_path is {frame['file_path']!r}, but '{file}' "
                              "does not exist; fix the entry (relative to the dataset folder, "
                              "'.exr' may be left out) or re-render the dataset with nrt-data.")
        img = read_exr(file)
        if images and img.shape != images[0].shape:
            raise _fail(file, f"is {img.shape[1]}x{img.shape[0]} pixels but "
                              f"{frames[0]['file_path']} is {images[0].shape[1]}x"
                              f"{images[0].shape[0]}; all images of a split share one size.")
        images.append(img)
        mats.append(m)
        env_index.append(env_names.index(env))
    height, width = images[0].shape[:2]
    intr = _intrinsics(meta, path, width, height)
    spec = None
    if (root / "scene.json").is_file():
        spec = _read_json(root / "scene.json").get("spec")
    return SceneDataset(
        root=root, split=split,
        images=torch.from_numpy(np.stack(images)),
        c2w=torch.from_numpy(np.stack(mats)).float(),
        intrinsics=intr,
        env_index=torch.tensor(env_index, dtype=torch.long),
        env_names=env_names, envmaps=envmaps,
        bbox=torch.tensor(bbox, dtype=torch.float32),
        ground_truth=_ground_truth(root),
        spec=spec,
    )
