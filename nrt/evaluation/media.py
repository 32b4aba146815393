"""Media as the report figures see them: any export read as property volumes, the planes a
scene's effects call for, and their middle slices.

A medium here is a mapping of property name to a float32 array indexed ``[z, y, x]`` (cell
centres, docs/conventions.md, "Grids"), per unit world length: ``sigma_a``, ``sigma_s`` (..., 3),
``sigma_t`` (..., 3), or (...) for a grey extinction, and ``g`` (...). A property-grid file
(``medium_grids.npz`` of stage 2 and the baseline, a dataset's ``ground_truth.npz``) gives
all four; stage 1's ``density_grid.npz`` gives ``sigma_t`` alone, grey.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nrt.data.grids import MEDIUM_GRIDS_FILE, load_property_grids
from nrt.errors import NrtError
from nrt.physics.volume import resample_cells
from nrt.stages.ea import DENSITY_GRID_FILE

PROPERTIES = ("sigma_a", "sigma_s", "sigma_t", "g")
CHANNELS = "RGB"
AXES = ("z", "y", "x")
"""Slice normals, in the order drawn; each slice is shown with world +Y (else +Z) up."""

Medium = dict[str, np.ndarray]


def medium_from_grids(grids: Mapping) -> Medium:
    """A medium from property grids (``sigma_a``, ``sigma_s`` (..., 3), ``g``; tensors or
    arrays), with ``sigma_t = sigma_a + sigma_s``."""
    out = {k: np.asarray(torch.as_tensor(grids[k]).detach().cpu(), np.float32)
           for k in ("sigma_a", "sigma_s", "g")}
    out["sigma_t"] = out["sigma_a"] + out["sigma_s"]
    return out


def read_medium(path: str | Path) -> Medium:
    """Any export as a medium: a property-grid ``.npz``, stage 1's ``density_grid.npz`` (a
    grey ``sigma_t``), or a run folder holding either (``medium_grids.npz`` first)."""
    path = Path(path).expanduser()
    if path.is_dir():
        found = [path / f for f in (MEDIUM_GRIDS_FILE, DENSITY_GRID_FILE) if (path / f).is_file()]
        if not found:
            raise NrtError(f"'{path}' holds no exported medium ({MEDIUM_GRIDS_FILE} of stage 2 "
                           f"or the baseline, {DENSITY_GRID_FILE} of stage 1). Pass a run "
                           "folder of nrt-train or a grid file.")
        path = found[0]
    if not path.is_file():
        raise NrtError(f"'{path}' is neither a run folder nor a grid file (.npz).")
    try:
        with np.load(path) as data:
            keys = set(data.files)
            density = np.asarray(data["density"], np.float32) if "density" in keys else None
    except Exception as exc:
        raise NrtError(f"'{path}' is not a readable NumPy .npz archive ({exc}).") from exc
    if density is not None and "sigma_a" not in keys:
        if density.ndim != 3 or not np.all(np.isfinite(density)):
            raise NrtError(f"'{path}': array 'density' must be a finite grid (Nz, Ny, Nx); "
                           f"it has shape {density.shape}.")
        return {"sigma_t": density}
    return medium_from_grids(load_property_grids(path))


def resolution(medium: Medium) -> int:
    """Cells per axis of the medium's grids (all are cubic, as every export is)."""
    return next(iter(medium.values())).shape[0]


def resampled(medium: Medium, cells: int) -> Medium:
    """The medium on ``cells``^3 cells of the same box (trilinear, cell-centred,
    :func:`~nrt.physics.volume.resample_cells`); as it is when already there."""
    out = {}
    for key, value in medium.items():
        if value.shape[0] == cells:
            out[key] = value
            continue
        grid = torch.from_numpy(value if value.ndim == 4 else value[..., None])
        new = resample_cells(grid.float(), cells).numpy()
        out[key] = new if value.ndim == 4 else new[..., 0]
    return out


@dataclass(frozen=True)
class Plane:
    """One scalar volume to draw: ``prop`` and, for an RGB property, ``channel`` (0-2) or
    None for the mean over RGB (``mean``: the channels differ) or a grey or scalar one."""

    prop: str
    channel: int | None = None
    mean: bool = False

    @property
    def label(self) -> str:
        if self.channel is not None:
            return f"{self.prop} {CHANNELS[self.channel]}"
        return f"{self.prop}, RGB mean" if self.mean else self.prop

    def volume(self, medium: Medium) -> np.ndarray | None:
        """This plane's scalar volume [z, y, x] of ``medium``; None where it lacks the
        property (stage 1 learns no sigma_a, sigma_s, g). A grey extinction stands for each
        channel."""
        value = medium.get(self.prop)
        if value is None or value.ndim == 3:
            return value
        return value[..., self.channel] if self.channel is not None else value.mean(-1)


def _grey(value: np.ndarray) -> bool:
    return value.ndim == 3 or bool(np.allclose(value, value[..., :1], rtol=1e-5, atol=1e-7))


def planes(reference: Medium, effects: Mapping | None = None, channels: str = "split"
           ) -> list[Plane]:
    """The planes to draw for the properties of ``reference`` (the truth when known), in
    :data:`PROPERTIES` order. ``g`` only when it varies (``effects.phase == varying_hg``,
    or without effects a g that is not one value). An RGB property is split into R, G, B
    with ``channels="split"`` unless it is grey (one value in every channel: a
    ``chromatic: false`` scene's sigma_t, stage 1's density), or its RGB mean with
    ``channels="mean"``."""
    if channels not in ("split", "mean"):
        raise NrtError(f"channels='{channels}': use split (R, G, B) or mean (their mean).")
    out: list[Plane] = []
    for prop in PROPERTIES:
        value = reference.get(prop)
        if value is None:
            continue
        if prop == "g":
            varies = (effects.get("phase") == "varying_hg" if effects is not None
                      else float(np.ptp(value)) > 1e-6)
            if varies:
                out.append(Plane("g"))
        elif _grey(value):
            out.append(Plane(prop))
        elif channels == "split":
            out += [Plane(prop, c) for c in range(3)]
        else:
            out.append(Plane(prop, mean=True))
    return out


def middle_slices(volume: np.ndarray) -> list[np.ndarray]:
    """The middle slice across each of :data:`AXES` of a volume [z, y, x], as images for
    ``imshow(origin="lower")``: normal z -> (y, x), normal y -> (z, x), normal x -> (y, z);
    row 0 is the lowest coordinate. The middle is cell ``N // 2``."""
    nz, ny, nx = volume.shape
    return [volume[nz // 2], volume[:, ny // 2, :], volume[:, :, nx // 2].T]


SLICE_AXES = {"z": ("x", "y"), "y": ("x", "z"), "x": ("z", "y")}
"""(horizontal, vertical) world axis of the slice across each axis, as
:func:`middle_slices` lays it out."""


@dataclass
class Source:
    """A medium named on the command line: its grids, and what its run folder tells (the
    dataset's ground truth, the scene's effects), None for a bare grid file."""

    medium: Medium
    label: str
    truth: Path | None = None
    effects: dict | None = None


def read_source(path: str | Path) -> Source:
    """A run folder of nrt-train (its export, its dataset's ``ground_truth.npz`` and its
    scene's effects; labelled by stage and folder name) or a grid file
    (:func:`read_medium`; labelled by its name)."""
    from omegaconf import OmegaConf

    from nrt.data.dataset import GROUND_TRUTH_FILE
    from nrt.evaluation.runs import read_run_folder
    from nrt.run_dirs import RUN_FILE

    path = Path(path).expanduser()
    medium = read_medium(path)
    if not (path.is_dir() and (path / RUN_FILE).is_file()):
        return Source(medium, path.stem if path.is_file() else path.name)
    _, info, cfg = read_run_folder(path)
    truth = Path(info["dataset_dir"]) / GROUND_TRUTH_FILE if "dataset_dir" in info else None
    effects = OmegaConf.to_container(cfg.scene.effects, resolve=True) if "scene" in cfg else None
    return Source(medium, f"{info.get('stage', '?')} {path.name}",
                  truth if truth is not None and truth.is_file() else None, effects)
