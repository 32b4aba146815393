"""HDR image I/O with OpenEXR: linear radiance, float32 RGB arrays (H, W, 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

from nrt.errors import DatasetError


def write_exr(path: str | Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) array as a float32, ZIP-compressed scanline EXR; a failed write
    (a full disk) raises ``OSError``."""
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise ValueError(f"write_exr expects (H, W, 3), got {rgb.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    try:
        with OpenEXR.File(header, {"RGB": rgb}) as f:
            f.write(str(path))
    except RuntimeError as exc:  # OpenEXR reports a failed write (a full disk) this way
        raise OSError(f"{exc}".strip()) from exc


def read_exr(path: str | Path) -> np.ndarray:
    """Read an EXR as float32 (H, W, 3): RGB, the RGB of RGBA, or grey ``Y`` replicated.

    Raises :class:`DatasetError` naming the file when it is missing, unreadable, has no
    colour channels, or holds NaN, Inf or negative radiance.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"EXR image '{path}' does not exist. Check the file_path entries "
                           "of the transforms file, or re-render the dataset with nrt-data.")
    try:
        with OpenEXR.File(str(path)) as f:
            channels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    except Exception as exc:  # OpenEXR raises plain RuntimeError/OSError on corrupt data
        raise DatasetError(f"EXR image '{path}' cannot be read ({exc}). The file is corrupt or "
                           "not an OpenEXR image; re-export or re-render it.") from exc
    if "RGB" in channels:
        rgb = channels["RGB"]
    elif "RGBA" in channels:
        rgb = channels["RGBA"][..., :3]
    elif "Y" in channels:
        rgb = np.repeat(channels["Y"][..., None], 3, axis=-1)
    else:
        raise DatasetError(f"EXR image '{path}' has channels {sorted(channels)} but no R, G, B "
                           "(or Y). Save it with RGB channels.")
    rgb = rgb.astype(np.float32)
    bad = ~np.isfinite(rgb)
    if bad.any():
        raise DatasetError(f"EXR image '{path}' holds {int(bad.sum())} NaN or Inf values. "
                           "Radiance must be finite; fix or re-render the image.")
    if (rgb < 0).any():
        raise DatasetError(f"EXR image '{path}' holds negative radiance (min {rgb.min():g}). "
                           "Radiance must be non-negative; fix or re-render the image.")
    return rgb
