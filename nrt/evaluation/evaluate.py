"""Evaluate a medium (property grids) against a dataset: what ``nrt-eval`` reports.

1. Property MSE x 10^2 against ``ground_truth.npz`` (:func:`nrt.metrics.property_mse`,
   after resampling the grids to the ground truth's resolution).
2. Novel-view synthesis under (by default novel) illumination: the held-out frames are
   re-rendered with Mitsuba ``volpath`` from the medium and compared with the photos
   (PSNR, SSIM, LPIPS after the log tonemap). ``noise_floor`` re-renders the true medium
   too: the PSNR that Monte Carlo noise alone leaves, the ceiling of any reconstruction.
3. Relighting: the medium (and the truth, when known) under an environment plus extra
   local lights, as EXR and PNG.

Metric names: ``mse_<property>_x100``; ``<metric>_<group>`` with group ``seen`` (frames
under the environments the medium was fitted under: a run's training environments; for a
property-grid file, whose training is unknown, the scene's ``environments.train``, else the
dataset's first environment), ``novel`` (under the others; absent when the dataset has a
single environment), ``env_<name>``; ``*_noise_floor_*`` for the true
medium; ``*_relit`` for relighting.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from nrt.data.dataset import SceneDataset
from nrt.data.exr import write_exr
from nrt.data.grids import resample_grids
from nrt.evaluation.images import comparison_panel, save_png
from nrt.evaluation.rerender import render_frames
from nrt.metrics import LPIPS, property_mse, psnr, ssim

log = logging.getLogger(__name__)


@dataclass
class Evaluation:
    """What an evaluation found: flat ``metrics``, per-frame rows, pictures (name -> (H, W,
    3) panel in [0, 1]) for previews and TensorBoard, and the re-rendered views (name ->
    (photo, re-render), linear (H, W, 3) radiance; ``novel`` lists those under illumination
    the medium was not fitted under) for ``report.png``."""

    metrics: dict[str, float] = field(default_factory=dict)
    frames: list[dict] = field(default_factory=list)
    pictures: dict[str, np.ndarray] = field(default_factory=dict)
    renders: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    novel: list[str] = field(default_factory=list)


def image_metrics(pred, ref, lpips: LPIPS | None = None) -> dict[str, float]:
    """PSNR, SSIM (and LPIPS) of two (H, W, 3) linear images after the log tonemap."""
    p, r = torch.as_tensor(pred).float(), torch.as_tensor(ref).float()
    out = {"psnr": float(psnr(p, r)), "ssim": float(ssim(p, r))}
    if lpips is not None:
        out["lpips"] = float(lpips(p, r))
    return out


def property_metrics(grids: Mapping, truth: Mapping, effects: dict) -> dict[str, float]:
    """Property MSE x 10^2 on the ground truth's cells (g unless isotropic); ``grids`` and
    ``truth`` cover the same box."""
    learned = resample_grids({k: torch.as_tensor(v) for k, v in grids.items()},
                             truth["g"].shape[0])
    with_g = effects["phase"] != "isotropic"
    return {f"mse_{k}_x100": float(v) for k, v in property_mse(learned, truth, with_g).items()}


def seen_environments(data: SceneDataset, trained: list[str]) -> list[str]:
    """The environments whose illumination the medium has seen: ``trained`` (a run's, or
    for a property-grid file the scene's training skies, :func:`named_environments`), or,
    when unknown (``trained`` empty), the dataset's first one, which every stage trains
    on. With a single environment, every frame is under seen illumination."""
    if trained:
        return list(trained)
    log.info("The medium's training environments are unknown: counting '%s', the first, "
             "as seen; the others as novel.", data.env_names[0])
    return list(data.env_names[:1])


def named_environments(data: SceneDataset, wanted: list[str | int] | None) -> list[str]:
    """The dataset's environments that ``wanted`` names (positions or names, as
    ``scene.environments.train``; null: all), those it lacks left out."""
    if wanted is None:
        return list(data.env_names)
    return [n for n in _names(data, wanted) if n in data.env_names]


def _names(data: SceneDataset, wanted: list[str | int]) -> list[str]:
    """``wanted`` as environment names: a position in the dataset's environments becomes
    its name, anything else (a name, a position it lacks) its string."""
    return [data.env_names[w] if isinstance(w, int) and 0 <= w < len(data.env_names)
            else str(w) for w in wanted]


def choose_environments(data: SceneDataset, wanted, trained: list[str]) -> list[str]:
    """Environment names to re-render under: ``novel`` (those the run did not train on;
    the trained ones if the dataset has no other), ``all``, or a list of names."""
    if wanted in ("novel", None):
        novel = [n for n in data.env_names if n not in trained]
        if not novel:
            log.warning("Dataset '%s' has no environment the run did not train on (%s): "
                        "re-rendering under the training illumination instead (novel views "
                        "only). Give the scene a second environment for novel illumination.",
                        data.root, trained)
        return novel or list(data.env_names)
    if wanted == "all":
        return list(data.env_names)
    names = _names(data, wanted)
    from nrt.errors import NrtError

    unknown = [n for n in names if n not in data.env_names]
    if unknown:
        raise NrtError(f"rerender.environments names {unknown}, which dataset '{data.root}' "
                       f"does not have; it has {data.env_names} (or use novel | all).")
    return names


def _mean(rows: list[dict], key: str) -> float:
    return float(np.mean([r[key] for r in rows]))


def rerender_metrics(grids: Mapping, effects: dict, data: SceneDataset, trained: list[str],
                     settings: Mapping, lpips: LPIPS | None, result: Evaluation) -> None:
    """Re-render the held-out frames of the chosen environments; compare with the photos.
    Frames under :func:`seen_environments` give the ``seen`` metrics, the others ``novel``."""
    trained = seen_environments(data, trained)
    envs = choose_environments(data, settings.get("environments", "novel"), trained)
    frames = [i for i in range(len(data)) if data.env_names[int(data.env_index[i])] in envs]
    if settings.get("max_views"):
        frames = frames[: int(settings["max_views"]) * len(envs)]
    spp = int(settings.get("spp") or (data.spec or {}).get("spp", 128))
    ours = render_frames(grids, effects, data, frames, spp, seed=1)
    floor = None
    if settings.get("noise_floor") and data.ground_truth is not None:
        floor = render_frames(data.ground_truth, effects, data, frames, spp, seed=2)
    for pos, frame in enumerate(frames):
        env = data.env_names[int(data.env_index[frame])]
        ref = data.images[frame].numpy()
        row = {"frame": frame, "environment": env, "trained_on": env in trained,
               **image_metrics(ours[pos], ref, lpips)}
        if floor is not None:
            row.update({f"{k}_noise_floor": v for k, v in image_metrics(floor[pos], ref).items()})
        result.frames.append(row)
        name = f"{env}_view{frame:03d}"
        result.pictures[name] = comparison_panel(ref, ours[pos])
        result.renders[name] = (ref, np.asarray(ours[pos]))
        if env not in trained:
            result.novel.append(name)
    keys = [k for k in result.frames[0] if k not in ("frame", "environment", "trained_on")]
    groups = {"novel": [r for r in result.frames if not r["trained_on"]],
              "seen": [r for r in result.frames if r["trained_on"]]}
    groups.update({f"env_{e}": [r for r in result.frames if r["environment"] == e] for e in envs})
    for group, rows in groups.items():
        for key in keys if rows else []:
            name = key.replace("_noise_floor", "")
            suffix = "_noise_floor" if key.endswith("_noise_floor") else ""
            result.metrics[f"{name}{suffix}_{group}"] = _mean(rows, key)
    result.metrics["rerender_spp"] = float(spp)


def relight(grids: Mapping, effects: dict, data: SceneDataset, settings: Mapping,
            out_dir: Path, lpips: LPIPS | None, result: Evaluation) -> None:
    """The medium under an environment plus extra local lights (the paper's teaser), and
    the true medium under the same lights when known; EXR + PNG and, with a truth, metrics."""
    env = settings.get("environment", 0)
    env_idx = env if isinstance(env, int) else data.env_names.index(str(env))
    frames = [i for i in range(len(data)) if int(data.env_index[i]) == env_idx]
    frames = [frames[int(v)] for v in settings.get("views", [0])]
    lights = [dict(light) for light in settings.get("lights", [])]
    spp = int(settings.get("spp") or (data.spec or {}).get("spp", 128))
    envmap = data.envmaps[env_idx].radiance.cpu().numpy() * float(
        settings.get("environment_scale", 1.0))
    ours = render_frames(grids, effects, data, frames, spp, seed=3, extra_lights=lights,
                         envmap=envmap)
    truth = None
    if data.ground_truth is not None:
        truth = render_frames(data.ground_truth, effects, data, frames, spp, seed=4,
                              extra_lights=lights, envmap=envmap)
    folder = out_dir / "relight"
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for pos, frame in enumerate(frames):
        write_exr(folder / f"ours_view{frame:03d}.exr", ours[pos])
        ref = truth[pos] if truth is not None else None
        if ref is not None:
            write_exr(folder / f"truth_view{frame:03d}.exr", ref)
            rows.append(image_metrics(ours[pos], ref, lpips))
        panel = comparison_panel(ref, ours[pos])
        save_png(folder / f"relit_view{frame:03d}.png", panel)
        result.pictures[f"relit_view{frame:03d}"] = panel
    for key in rows[0] if rows else []:
        result.metrics[f"{key}_relit"] = _mean(rows, key)
