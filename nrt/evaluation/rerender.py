"""Re-render property grids with Mitsuba ``volpath`` from a dataset's cameras.

The same scene description as the dataset renderer (:mod:`nrt.mitsuba.scene`):
a medium built for the scene's effects (spatially varying g through the ``nrt_hg_grid``
plugin), the frame's environment map, the scene's point emitters, plus optional extra
local lights for relighting. Seeds differ from the dataset's, so a re-render of the true
medium differs from the photos by Monte Carlo noise alone.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from nrt.cameras import fov_x_deg
from nrt.data.dataset import SceneDataset
from nrt.mitsuba.render import ViewRenderer
from nrt.mitsuba.scene import scene_dict
from nrt.mitsuba.variant import select_variant

SEED_BASE = 7_000_003
"""Re-render seeds start here (datasets use seeds below 10^6)."""


def numpy_grids(grids: Mapping) -> dict[str, np.ndarray]:
    return {k: np.asarray(torch.as_tensor(grids[k]).detach().cpu(), np.float32)
            for k in ("sigma_a", "sigma_s", "g")}


def render_frames(grids: Mapping | None, effects: dict, data: SceneDataset,
                  frames: Sequence[int], spp: int, seed: int = 0,
                  extra_lights: list[dict] | None = None,
                  envmap: np.ndarray | None = None) -> np.ndarray:
    """Linear RGB renders (F, H, W, 3) of ``grids`` (None: no medium) seen by the cameras
    of ``frames`` of ``data``, each under its own environment (or ``envmap`` for all)."""
    mi = select_variant("auto")
    spec = {"bbox": data.bbox.tolist(), "effects": effects}
    arrays = numpy_grids(grids) if grids is not None else None
    intr = data.intrinsics
    out = np.zeros((len(frames), intr.height, intr.width, 3), np.float32)
    groups: dict[int, list[int]] = {}
    for pos, frame in enumerate(frames):
        key = -1 if envmap is not None else int(data.env_index[frame])
        groups.setdefault(key, []).append(pos)
    for env, positions in groups.items():
        radiance = envmap if env < 0 else data.envmaps[env].radiance.cpu().numpy()
        renderer = ViewRenderer(mi, scene_dict(
            mi, spec, arrays, radiance, intr.width, intr.height,
            fov_x_deg(intr, f"Dataset '{data.root}' (transforms_test.json)"), spp,
            extra_lights=extra_lights))
        for pos in positions:
            frame = int(frames[pos])
            out[pos] = renderer.render(data.c2w[frame].cpu().numpy(), spp,
                                       SEED_BASE + 1009 * seed + frame)
    return out
