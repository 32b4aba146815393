"""Property grids on disk, in the layout of a dataset's ``ground_truth.npz``.

A property-grid file is a NumPy ``.npz`` archive with ``sigma_a``, ``sigma_s``
(Nz, Ny, Nx, 3) and ``g`` (Nz, Ny, Nx), per unit world length, at cell centres and
indexed ``[z, y, x]`` (:mod:`nrt.physics.volume`), plus ``bbox`` (2, 3) where known. The
dataset's ground truth, every stage's export (``medium_grids.npz``) and ``nrt-eval``
read and write this one format, so any two can be compared cell by cell.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from nrt.errors import DatasetError
from nrt.files import atomic_write
from nrt.physics.volume import resample_cells

PROPERTY_KEYS = ("sigma_a", "sigma_s", "g")
MEDIUM_GRIDS_FILE = "medium_grids.npz"
"""Where each stage that learns a medium exports it, in its run folder."""


def save_property_grids(path: str | Path, grids: Mapping, bbox) -> Path:
    """Write ``grids`` (tensors or arrays) and ``bbox`` as float32 into ``path`` (.npz),
    replacing it atomically (:func:`nrt.files.atomic_write`)."""
    path = Path(path)
    arrays = {k: np.asarray(torch.as_tensor(grids[k]).detach().cpu(), np.float32)
              for k in PROPERTY_KEYS}
    bbox = np.asarray(torch.as_tensor(bbox).detach().cpu(), np.float32)
    with atomic_write(path, "the property grids") as f:
        np.savez_compressed(f, bbox=bbox, **arrays)
    return path


def _fail(path: Path, message: str) -> DatasetError:
    return DatasetError(f"Property grids '{path}': {message}")


def load_property_grids(path: str | Path) -> dict[str, torch.Tensor]:
    """Read and validate a property-grid file; returns float32 tensors (and ``bbox`` when
    the file has one). Errors name the file, the array and the expected shape."""
    path = Path(path)
    try:
        with np.load(path) as data:
            arrays = {k: data[k] for k in (*PROPERTY_KEYS, "bbox") if k in data}
    except Exception as exc:
        raise _fail(path, f"is not a readable NumPy .npz archive ({exc}); write it with "
                          "numpy.savez (sigma_a, sigma_s, g[, bbox]) or remove it.") from exc
    missing = set(PROPERTY_KEYS) - set(arrays)
    if missing:
        raise _fail(path, f"lacks arrays {sorted(missing)}; it needs sigma_a, sigma_s "
                          "(Nz, Ny, Nx, 3) and g (Nz, Ny, Nx).")
    grid = arrays["g"].shape
    if len(grid) != 3:
        raise _fail(path, f"array 'g' has shape {grid}, expected a grid (Nz, Ny, Nx).")
    for key in ("sigma_a", "sigma_s"):
        if arrays[key].shape != (*grid, 3):
            raise _fail(path, f"array '{key}' has shape {arrays[key].shape}, expected "
                              f"{(*grid, 3)} with g of shape (Nz, Ny, Nx).")
    if "bbox" in arrays and arrays["bbox"].shape != (2, 3):
        raise _fail(path, f"array 'bbox' has shape {arrays['bbox'].shape}, expected (2, 3).")
    for key, a in arrays.items():
        if not np.all(np.isfinite(a)):
            raise _fail(path, f"array '{key}' holds NaN or Inf values.")
    return {k: torch.from_numpy(np.asarray(v, np.float32)) for k, v in arrays.items()}


def resample_grids(grids: Mapping[str, torch.Tensor], resolution: int
                   ) -> dict[str, torch.Tensor]:
    """Property grids on ``resolution``^3 cells of the same box: the three resampled
    together by :func:`~nrt.physics.volume.resample_cells` (trilinear, cell-centred,
    edge-clamped, float32), the extinctions clamped at 0; returned as they are when already
    at that resolution."""
    if all(s == resolution for s in grids["g"].shape):
        return {k: grids[k] for k in PROPERTY_KEYS}
    stacked = torch.cat((grids["sigma_a"], grids["sigma_s"], grids["g"].unsqueeze(-1)), -1)
    out = resample_cells(stacked.float(), resolution)
    return {"sigma_a": out[..., :3].clamp_min(0), "sigma_s": out[..., 3:6].clamp_min(0),
            "g": out[..., 6]}
