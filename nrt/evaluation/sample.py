"""Sample new media from a generative run and score them: what ``nrt-sample`` reports.

A generative stage-2 run (``nrt-train stage=rte mode=generative scene=family``) learned one
latent code per family member and a decoder from any code to a medium
(:class:`LatentMediumModel`). ``nrt-sample``:

1. fits ``N(mu, Sigma)`` to the learned codes (:mod:`nrt.evaluation.latent_gaussian`) and
   draws ``n`` codes from it (``seed``; at a ``temperature``), or with a ``bandwidth`` from
   a smoothed bootstrap of the codes;
2. decodes each to property grids (``property_grids_for``), checked finite and valid
   (sigma >= 0, |g| < 1), and exports them as ``medium_grids.npz`` and Mitsuba volumes;
3. renders each with Mitsuba ``volpath`` (the dataset renderer's scene, via
   :func:`nrt.evaluation.rerender.render_frames`) from the family's held-out cameras under
   its shared training sky and its held-back sky;
4. computes FID on random crops (:class:`nrt.metrics.FID`), the paper's two columns:
   ``fid_train_illumination``, the samples under the training sky against the members'
   ground-truth images under it, and ``fid_novel_illumination``, the samples under the
   held-back sky against the members' images under that sky. With ``truth_reference`` the
   members' true media, rendered exactly as the samples are and taken in turn to make up
   ``n`` media (the samples' image and crop counts; fresh crop positions on repeats), are
   scored the same way (``*_truth``): what a generator that reproduced its training
   members would score at these counts, FID's bias at this size. With
   ``recon_reference`` the members' reconstructions (each member's own medium, from its
   learned code and whatever the run keeps per member) are rendered and scored the same
   way, with the true media's render seeds (``*_recon``): truth -> recon is what the
   reconstruction loses, recon -> samples what sampling new codes adds. With
   ``unseen_reference`` ``n`` media the family's own generator draws after its members
   (:func:`unseen_media`: new media of the family, seen by no run) are rendered and scored
   the same way (``*_unseen``): what a generator that draws new members exactly as the
   family does would score, where ``*_truth`` is what one that repeats its members would;
5. scores each member's reconstruction (its own medium) against its ground truth
   (property MSE x 10^2, ``recon_mse_<property>_x100`` the mean over members);
6. draws a picture of the samples per sky and a strip of media decoded along
   ``z(t) = (1 - t) z_a + t z_b`` between two learned codes, with each step's property MSE
   to both endpoints.

Images stay linear radiance; FID and the pictures map both sets of a column through
``log1p(x) / log1p(white)``, clamped to [0, 1], with ``white`` the median over the column's
real images of each image's largest value (:func:`white_of`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from nrt.data.dataset import SceneDataset, load_dataset
from nrt.data.exr import write_exr
from nrt.data.family import Family, member_scenes, unseen_member_scenes
from nrt.data.grids import MEDIUM_GRIDS_FILE, PROPERTY_KEYS, save_property_grids
from nrt.data.media import medium_grids
from nrt.data.spec import resolve_scene
from nrt.errors import NrtError
from nrt.evaluation.evaluate import property_metrics
from nrt.evaluation.images import display, save_png
from nrt.evaluation.latent_gaussian import (
    LatentGaussian,
    fit_latent_gaussian,
    scott_bandwidth,
)
from nrt.evaluation.rerender import render_frames
from nrt.metrics import FID
from nrt.modules.fields.latent_grid import CodeKernel

log = logging.getLogger(__name__)

MIN_CROP = 16
AUTO_FOLD_STEPS = 2000
"""``fold.steps=auto`` on a run with member offsets: at `cpu` (K = 16) 2000 steps leave 13 %
of the fit's start and sample at FID 62.6 / 58.8, against 85.6 / 76.7 unfolded
(docs/generative.md, "Sampling")."""


class LatentMediumModel(Protocol):
    """What ``nrt-sample`` needs of a generative stage-2 run (its scene family,
    :class:`~nrt.stages.family.SceneFamily`): ``codes`` (K, d_z), one row per family member
    in the family's order, and the medium decoded from any code on ``resolution``^3 cells
    in the format of ``Stage.property_grids`` (CPU, no gradient), and each member's own
    medium (its code, and whatever else the run keeps per member); where each member's
    medium holds a feature offset, the fold that takes them into the shared decoder."""

    codes: torch.Tensor
    holds_member_offsets: bool

    def fold_offsets(self, steps: int, lr: float, kernel: CodeKernel | None = None
                     ) -> dict[str, float]: ...

    def member_names(self) -> list[str]: ...

    def property_grids_for(self, code: torch.Tensor, resolution: int
                           ) -> dict[str, torch.Tensor]: ...

    def member_property_grids(self, member: int, resolution: int
                              ) -> dict[str, torch.Tensor]: ...

    def medium_bbox(self) -> torch.Tensor | None: ...


@dataclass
class FamilyData:
    """The family as ``nrt-sample`` uses it: ``cameras`` (member 0's held-out split: the
    camera rig and both skies every member shares), each member's ground-truth grids, the
    scene's effects and, where known, the family's scene config (``scene``, with its
    ``family`` key: what draws new media of the family, :func:`unseen_media`);
    ``unseen_checked``: :func:`check_unseen` passed on it (the check resolves the first
    member's medium, seconds at ``cpu``, so it runs once)."""

    family: Family
    cameras: SceneDataset
    truths: list[dict[str, torch.Tensor]]
    effects: dict
    scene: dict | None = None
    unseen_checked: bool = field(default=False, compare=False, repr=False)

    @property
    def skies(self) -> dict[str, str]:
        """Column name -> environment: ``train`` (shared training sky), ``novel`` (held back)."""
        return {"train": self.family.train_environment, "novel": self.family.heldout_environment}


def load_family_data(family: Family, effects: dict, scene: dict | None = None) -> FamilyData:
    """Read the family's camera rig and its members' ground truths (all must have one);
    ``scene``: the family's scene config (the run's ``scene``), kept as it is."""
    cameras = load_dataset(family.member(0).folder, "test")
    truths = []
    for member in family.members:
        truth = load_dataset(member.folder, "test").ground_truth
        if truth is None:
            raise NrtError(f"Family member '{member.name}' ({member.folder}) has no "
                           "ground_truth.npz: nrt-sample scores reconstructions against each "
                           "member's true medium. Render the family with nrt-data scene=family.")
        truths.append(truth)
    return FamilyData(family, cameras, truths, effects, scene)


def check_unseen(data: FamilyData) -> None:
    """Refuse to draw new media of the family (:func:`unseen_media`) from a scene config
    that does not draw its first member again: a run trained on another config of the
    family's name would otherwise be scored against media of another family. Once per
    ``data``: a check that passed is not repeated."""
    if data.unseen_checked:
        return
    if not data.scene or "family" not in data.scene:
        raise NrtError("fid.unseen_reference=true draws new media of the family from its "
                       "scene config, but this run's config holds no scene.family; set "
                       "fid.unseen_reference=false.")
    first = medium_grids(resolve_scene(member_scenes(data.scene)[0]))
    if any(not torch.allclose(torch.as_tensor(first[k]), data.truths[0][k].float(), atol=1e-5)
           for k in PROPERTY_KEYS):
        raise NrtError(f"fid.unseen_reference=true: the run's scene config does not draw the "
                       f"first member of the family '{data.family.root}' again (its medium "
                       "differs from that member's ground_truth.npz): the run was trained on "
                       "another family, or the family was rendered from another config. "
                       "Sample the run with the family it was trained on, or set "
                       "fid.unseen_reference=false.")
    data.unseen_checked = True


def unseen_media(data: FamilyData, count: int, start: int = 0
                 ) -> list[dict[str, torch.Tensor]]:
    """The true media (the ground-truth layout) of ``count`` new members of the family:
    drawn by its scene config (``data.scene``, checked by :func:`check_unseen`) from the
    seeds after its members' and ``start`` more
    (:func:`~nrt.data.family.unseen_member_scenes`), never rendered as photos nor trained
    on."""
    check_unseen(data)
    return [{k: torch.as_tensor(v) for k, v in medium_grids(resolve_scene(spec)).items()}
            for spec in unseen_member_scenes(data.scene, count, start)]


@dataclass
class SampleSettings:
    """``conf/sample.yaml``'s keys in one place, with its defaults (see there for their
    meaning)."""

    n: int = 16
    seed: int = 0
    resolution: int | None = None
    shrinkage: float | str = "auto"
    temperature: float = 1.0
    bandwidth: float | str | None = None
    views: int | None = 4
    spp: int | None = None
    export_mitsuba: bool = True
    export_exr: bool = True
    fid_crop: int | None = None
    fid_n_crops: int = 2
    fid_real_views: int | None = 8
    fid_truth_reference: bool = True
    fid_recon_reference: bool = False
    fid_unseen_reference: bool = False
    interpolate_members: Sequence[int] | None = None
    interpolate_steps: int = 7
    picture_max_samples: int = 16
    fold_steps: int | str = "auto"
    fold_lr: float = 0.02
    fold_bandwidth: float | str | None = None

    def fold_steps_for(self, member_offsets: bool) -> int:
        """The fold's Adam steps for a run whose medium holds member offsets (or not):
        ``fold_steps`` as given, or for ``"auto"`` :data:`AUTO_FOLD_STEPS` where there are
        offsets to fold and 0 where there are none."""
        if self.fold_steps == "auto":
            return AUTO_FOLD_STEPS if member_offsets else 0
        return int(self.fold_steps)

    def bandwidth_for(self, count: int, dim: int) -> float | None:
        """The smoothed bootstrap's bandwidth for K = ``count`` codes of ``dim`` values
        (``"scott"``: Scott's rule), or None to draw from the Gaussian."""
        return bandwidth_value(self.bandwidth, count, dim)

    def fold_bandwidth_for(self, count: int, dim: int) -> float | None:
        """The bandwidth of the codes the fold also fits around each member (as
        :meth:`bandwidth_for`), or None to fit at the codes alone."""
        return bandwidth_value(self.fold_bandwidth, count, dim)

    def check(self, members: int | None = None) -> None:
        """Refuse values no sampling can use (before anything is loaded or rendered)."""
        def whole(value, least: int) -> bool:
            return isinstance(value, int) and not isinstance(value, bool) and value >= least
        bad = [(k, v, m) for k, v, least, m in (
            ("n", self.n, 1, "the number of media to sample, >= 1"),
            ("render.views", self.views, 1, "held-out cameras per sky, >= 1 (null: all)"),
            ("render.spp", self.spp, 1, "samples per pixel, >= 1 (null: the dataset's)"),
            ("resolution", self.resolution, 2, "cells per axis, >= 2 (null: the truth's)"),
            ("fid.crop", self.fid_crop, MIN_CROP, f"crop pixels, >= {MIN_CROP} (null: auto)"),
            ("fid.n_crops", self.fid_n_crops, 1, "crops per image, >= 1"),
            ("fid.real_views", self.fid_real_views, 1, "images per member, >= 1 (null: all)"),
            ("interpolate.steps", self.interpolate_steps, 2, "media along the strip, >= 2"),
            ("picture.max_samples", self.picture_max_samples, 1, "samples drawn, >= 1"),
            ("fold.steps", self.fold_steps, 0,
             "Adam steps of the offsets' fold, >= 0 (0: none), or auto"))
            if v is not None and not whole(v, least) and not (k == "fold.steps" and v == "auto")
            or v is None and k in ("n", "fid.n_crops", "interpolate.steps",
                                   "picture.max_samples", "fold.steps")]
        def positive(value, least_open: bool = True) -> bool:
            return not isinstance(value, bool) and isinstance(value, int | float) and (
                0 < value < float("inf") if least_open else 0 <= value < float("inf"))
        if not positive(self.fold_lr):
            bad.append(("fold.lr", self.fold_lr, "the fold's Adam learning rate, a number > 0"))
        if not positive(self.temperature):
            bad.append(("gaussian.temperature", self.temperature,
                        "the draws' spread about the mean in units of the fit's, a number > 0 "
                        "(1: the fitted Gaussian)"))
        if self.bandwidth is not None and self.bandwidth != "scott" \
                and not positive(self.bandwidth, least_open=False):
            bad.append(("gaussian.bandwidth", self.bandwidth,
                        "null (draw from the Gaussian), scott or a number >= 0 (a smoothed "
                        "bootstrap of the learned codes)"))
        if self.fold_bandwidth is not None and self.fold_bandwidth != "scott" \
                and not positive(self.fold_bandwidth, least_open=False):
            bad.append(("fold.bandwidth", self.fold_bandwidth,
                        "null (fit at the learned codes alone), scott or a number >= 0 (also "
                        "at codes drawn around each member by a smoothed bootstrap)"))
        if bad:
            key, value, meaning = bad[0]
            raise NrtError(f"{key}={value!r}: must be {meaning}. "
                           "For example: nrt-sample run=<generative stage-2 run> n=16.")
        pair = self.interpolate_members
        if pair is not None and (len(pair) != 2 or pair[0] == pair[1] or any(
                not isinstance(i, int) or members is not None and not 0 <= i < members
                for i in pair)):
            top = f"0..{members - 1}" if members is not None else "member positions"
            raise NrtError(f"interpolate.members={list(pair)}: give two different members "
                           f"({top}) to interpolate between, or null for the two codes "
                           "farthest apart.")


def bandwidth_value(bandwidth: float | str | None, count: int, dim: int) -> float | None:
    """A bandwidth setting as a number for K = ``count`` codes of ``dim`` values
    (``"scott"``: Scott's rule; None stays None)."""
    if bandwidth == "scott":
        return scott_bandwidth(count, dim)
    return None if bandwidth is None else float(bandwidth)


def fold(model: LatentMediumModel, settings: SampleSettings) -> dict[str, float]:
    """Fold ``model``'s member offsets into its shared decoder as ``settings`` say
    (``fold_steps``, ``fold_lr``; with ``fold_bandwidth``, also around each code, at draws
    of the smoothed bootstrap of the Gaussian fitted to the codes): the fold's figures, or
    {} where there is nothing to fold."""
    steps = settings.fold_steps_for(model.holds_member_offsets)
    if not steps:
        return {}
    codes = model.codes.detach().float().cpu()
    bandwidth = settings.fold_bandwidth_for(*codes.shape)
    kernel = None
    if bandwidth is not None:
        gauss = fit_latent_gaussian(codes, settings.shrinkage)
        def kernel(members: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
            return gauss.around(members, bandwidth, generator)
    figures = model.fold_offsets(steps, settings.fold_lr, kernel)
    return figures if bandwidth is None else {**figures, "fold_bandwidth": bandwidth}


@dataclass
class SampleResult:
    """What a sampling found: flat ``metrics``, per-member reconstruction rows, the
    interpolation rows, the fitted Gaussian and the sampled codes."""

    metrics: dict[str, float] = field(default_factory=dict)
    members: list[dict] = field(default_factory=list)
    interpolation: list[dict] = field(default_factory=list)
    gaussian: LatentGaussian | None = None
    samples: torch.Tensor | None = None
    pictures: dict[str, np.ndarray] = field(default_factory=dict)


def check_medium(grids: Mapping[str, torch.Tensor], what: str) -> dict[str, torch.Tensor]:
    """``grids``' property arrays as float32 CPU tensors, refused unless finite with
    sigma >= 0 and |g| < 1 (what Mitsuba's volumes and the HG phase need)."""
    out = {k: torch.as_tensor(grids[k]).detach().float().cpu() for k in PROPERTY_KEYS}
    finite = all(torch.isfinite(v).all() for v in out.values())
    if not finite or (out["sigma_a"] < 0).any() or (out["sigma_s"] < 0).any() \
            or (out["g"].abs() >= 1).any():
        raise NrtError(f"The medium decoded for {what} is not a valid medium (finite, "
                       "sigma >= 0, |g| < 1): the generative run's decoder produced "
                       "non-physical values; its training may have diverged.")
    return out


def decode(model: LatentMediumModel, code: torch.Tensor, resolution: int, what: str
           ) -> dict[str, torch.Tensor]:
    """The checked medium of ``code`` (d_z,) on ``resolution``^3 cells."""
    with torch.no_grad():
        grids = model.property_grids_for(code.detach().float().cpu(), int(resolution))
    return check_medium(grids, what)


def sky_frames(cameras: SceneDataset, environment: str, views: int | None) -> list[int]:
    """The first ``views`` held-out frames (all for None) under ``environment``."""
    env = cameras.env_names.index(environment)
    frames = [i for i in range(len(cameras)) if int(cameras.env_index[i]) == env]
    return frames[:views] if views else frames


def render_medium(grids: Mapping, data: FamilyData, frames: dict[str, list[int]], spp: int,
                  seed: int) -> dict[str, np.ndarray]:
    """Linear renders (V, H, W, 3) of one medium per column (``train``, ``novel``)."""
    return {col: render_frames(grids, data.effects, data.cameras, idx, spp, seed=seed)
            for col, idx in frames.items()}


def real_images(data: FamilyData, environment: str, per_member: int | None) -> torch.Tensor:
    """Every member's ground-truth images under ``environment`` (training and held-out
    views; the first ``per_member`` of each for a number), (M, H, W, 3) linear."""
    out = []
    for member in data.family.members:
        images = []
        for split in ("train", "test"):
            split_data = load_dataset(member.folder, split)
            env = split_data.env_names.index(environment)
            images.append(split_data.images[split_data.env_index == env])
        images = torch.cat(images)
        out.append(images[:per_member] if per_member else images)
    return torch.cat(out)


def fid_score(fid: FID, real: torch.Tensor, fake: torch.Tensor) -> float:
    """FID of ``fake`` against ``real`` (linear images), both through ``fid.white``."""
    fid.reset()
    fid.update(real, real=True)
    fid.update(fake, real=False)
    return float(fid.compute())


def reconstruction(model: LatentMediumModel, data: FamilyData, resolution: int
                   ) -> tuple[list[dict], list[dict[str, torch.Tensor]]]:
    """Each member's own medium (its code, and whatever the run keeps per member) against
    its ground truth: a row per member (``member``, ``name``, ``mse_<property>_x100``) and
    the decoded grids."""
    rows, media = [], []
    for k, (name, truth) in enumerate(zip(model.member_names(), data.truths, strict=True)):
        with torch.no_grad():
            grids = check_medium(model.member_property_grids(k, int(resolution)),
                                 f"member {k} ({name})")
        rows.append({"member": k, "name": name,
                     **property_metrics(grids, truth, data.effects)})
        media.append(grids)
    return rows, media


def reference_renders(media: Sequence[Mapping], data: FamilyData, frames: dict[str, list[int]],
                      spp: int, seed: int, n: int) -> dict[str, list[np.ndarray]]:
    """``media`` rendered as the samples are (medium k with render seed ``seed + k``) and
    taken in turn to make up ``n`` media: the samples' image and crop counts, per sky."""
    renders: dict[str, list[np.ndarray]] = {col: [] for col in frames}
    for k, grids in enumerate(media):
        for col, stack in render_medium(grids, data, frames, spp, seed=seed + k).items():
            renders[col].append(stack)
    return {col: [stacks[i % len(stacks)] for i in range(n)] for col, stacks in renders.items()}


def farthest_pair(codes: torch.Tensor) -> tuple[int, int]:
    """The two codes farthest apart (Euclidean), lowest indices first on ties."""
    dist = torch.cdist(codes.detach().double(), codes.detach().double())
    flat = int(torch.argmax(dist))
    a, b = divmod(flat, dist.shape[1])
    return (min(a, b), max(a, b))


def interpolation(model: LatentMediumModel, pair: tuple[int, int], steps: int,
                  resolution: int, effects: dict
                  ) -> tuple[list[dict[str, torch.Tensor]], list[dict]]:
    """Media along ``z(t) = (1 - t) z_a + t z_b``, t = 0, 1/(steps-1), ..., 1, and a row
    per step with t and the property MSE x 10^2 to both endpoints' media."""
    z_a, z_b = (model.codes[i].detach().float().cpu() for i in pair)
    ts = torch.linspace(0, 1, steps)
    media = [decode(model, (1 - t) * z_a + t * z_b, resolution, f"interpolation t={t:.3f}")
             for t in ts.tolist()]
    rows = []
    for t, grids in zip(ts.tolist(), media, strict=True):
        row = {"t": t}
        for end, ref in (("a", media[0]), ("b", media[-1])):
            row.update({k.replace("_x100", f"_to_{end}_x100"): v for k, v in
                        property_metrics(grids, ref, effects).items()})
        rows.append(row)
    return media, rows


def tile(images: Sequence[np.ndarray], columns: int, scale: float, gap: int = 2) -> np.ndarray:
    """Linear (H, W, 3) images as one display picture in [0, 1], ``columns`` per row,
    log-tonemapped with the common ``scale`` (so brightness compares across tiles)."""
    h, w, _ = images[0].shape
    rows = -(-len(images) // columns)
    out = np.ones((rows * (h + gap) - gap, columns * (w + gap) - gap, 3))
    for i, img in enumerate(images):
        r, c = divmod(i, columns)
        out[r * (h + gap):r * (h + gap) + h, c * (w + gap):c * (w + gap) + w] = display(img,
                                                                                      scale)
    return out


def white_of(real: torch.Tensor) -> float:
    """A column's white: the median over its real images (N, H, W, 3) of each image's
    largest value. The typical image's brightest pixel, so that the few views with the sun
    in them (100x brighter at tiny) do not darken everything else."""
    return float(real.amax(dim=(1, 2, 3)).median().clamp_min(1e-6))


def export_medium(folder: Path, grids: Mapping, bbox: torch.Tensor, effects: dict,
                  mitsuba: bool) -> None:
    """``medium_grids.npz`` and (``mitsuba``) ``volumes/`` for one medium."""
    from nrt.mitsuba.export import write_medium_files
    from nrt.mitsuba.variant import select_variant

    folder.mkdir(parents=True, exist_ok=True)
    save_property_grids(folder / MEDIUM_GRIDS_FILE, grids, bbox)
    if mitsuba:
        mi = select_variant("auto")
        write_medium_files(mi, folder / "volumes", grids, bbox, effects)


def _fid_crop(settings: SampleSettings, cameras: SceneDataset) -> int:
    side = min(cameras.intrinsics.width, cameras.intrinsics.height)
    crop = settings.fid_crop or max(MIN_CROP, side // 2)
    if crop > side:
        raise NrtError(f"fid.crop={crop} does not fit the family's images of {side} pixels: "
                       f"choose fid.crop <= {side} (null: half the image).")
    return crop


def make_fid(settings: SampleSettings, cameras: SceneDataset, white: float = 1.0) -> FID:
    """The FID metric of ``settings`` (crop, crops per image); errors name nrt-weights."""
    return FID(crop=_fid_crop(settings, cameras), n_crops=settings.fid_n_crops, white=white,
               seed=settings.seed)


def sample_media(model: LatentMediumModel, data: FamilyData, settings: SampleSettings,
                 out_dir: Path, fid: FID | None) -> SampleResult:
    """Steps 1-6 of the module docstring; writes into ``out_dir`` (``samples/``, pictures,
    ``latent_gaussian.npz``) and returns what it measured (``fid`` None: no FID)."""
    timings: dict[str, float] = {}
    start = time.perf_counter()
    result = SampleResult()
    codes = model.codes.detach().float().cpu()
    if codes.shape[0] != len(data.family):
        raise NrtError(f"The run holds {codes.shape[0]} codes but its family "
                       f"'{data.family.root}' has {len(data.family)} members: sample the "
                       "family the run was trained on.")
    bbox = model.medium_bbox()
    bbox = (bbox if bbox is not None else data.cameras.bbox).detach().float().cpu()
    res = int(settings.resolution or data.truths[0]["g"].shape[0])
    spp = int(settings.spp or (data.cameras.spec or {}).get("spp", 128))
    frames = {col: sky_frames(data.cameras, env, settings.views)
              for col, env in data.skies.items()}

    result.gaussian = gauss = fit_latent_gaussian(codes, settings.shrinkage)
    bandwidth = settings.bandwidth_for(gauss.count, gauss.dim)
    result.samples = samples = gauss.sample(settings.n, settings.seed, settings.temperature,
                                            bandwidth)
    np.savez(out_dir / "latent_gaussian.npz", codes=codes.numpy(),
             mean=gauss.mean.numpy(), cov=gauss.cov.numpy(), shrinkage=gauss.shrinkage,
             samples=samples.numpy(), names=np.array(model.member_names()))

    renders: dict[str, list[np.ndarray]] = {col: [] for col in frames}
    for i, code in enumerate(samples):
        grids = decode(model, code, res, f"sample {i}")
        folder = out_dir / "samples" / f"sample{i:03d}"
        export_medium(folder, grids, bbox, data.effects, settings.export_mitsuba)
        images = render_medium(grids, data, frames, spp, seed=1 + i)
        for col, stack in images.items():
            renders[col].append(stack)
            for frame, img in zip(frames[col], stack, strict=True):
                if settings.export_exr:
                    write_exr(folder / f"{data.skies[col]}_view{frame:03d}.exr", img)
    timings["decode_render_export_s"] = time.perf_counter() - start

    t0 = time.perf_counter()
    result.members, recon_media = reconstruction(model, data, res)
    for key in result.members[0]:
        if key.startswith("mse_"):
            result.metrics[f"recon_{key}"] = float(np.mean([r[key] for r in result.members]))
    timings["reconstruction_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    reals = {col: real_images(data, env, settings.fid_real_views)
             for col, env in data.skies.items()}
    if fid is not None:
        # the true media and the reconstructions share render seeds: equal media, equal FID
        wanted = {"truth": settings.fid_truth_reference,
                  "recon": settings.fid_recon_reference,
                  "unseen": settings.fid_unseen_reference}
        media = {"truth": lambda: data.truths, "recon": lambda: recon_media,
                 "unseen": lambda: unseen_media(data, settings.n)}
        references = {name: reference_renders(media[name](), data, frames, spp,
                                              1 + settings.n, settings.n)
                      for name, on in wanted.items() if on}
        for col, real in reals.items():
            fid.white = white_of(real)
            fake = torch.as_tensor(np.concatenate(renders[col]))
            result.metrics[f"fid_{col}_illumination"] = fid_score(fid, real, fake)
            for name, reference in references.items():
                fid.reset(real=False)
                fid.update(torch.as_tensor(np.concatenate(reference[col])), real=False)
                result.metrics[f"fid_{col}_illumination_{name}"] = float(fid.compute())
            result.metrics[f"fid_{col}_real_crops"] = float(fid.count(True))
            result.metrics[f"fid_{col}_sample_crops"] = float(len(fake) * fid.n_crops)
        result.metrics["fid_crop"] = float(fid.crop)
    timings["fid_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    pair = (tuple(settings.interpolate_members) if settings.interpolate_members is not None
            else farthest_pair(codes))
    strip, result.interpolation = interpolation(model, pair, settings.interpolate_steps, res,
                                                data.effects)
    strip_rows = []
    for col in frames:  # a row per sky, each with its own white
        images = [render_frames(g, data.effects, data.cameras, frames[col][:1], spp,
                                seed=10_000 + j)[0] for j, g in enumerate(strip)]
        row = tile(images, len(images), float(np.log1p(white_of(reals[col]))))
        strip_rows += [row, np.ones((2, row.shape[1], 3))]
    result.pictures["interpolation"] = np.concatenate(strip_rows[:-1], 0)
    for col in frames:
        shown = [stack[0] for stack in renders[col][:settings.picture_max_samples]]
        result.pictures[f"samples_{data.skies[col]}"] = tile(
            shown, int(np.ceil(np.sqrt(len(shown)))), float(np.log1p(white_of(reals[col]))))
    for name, picture in result.pictures.items():
        save_png(out_dir / f"{name}.png", picture)
    timings["interpolation_pictures_s"] = time.perf_counter() - t0
    result.metrics["interpolation_member_a"], result.metrics["interpolation_member_b"] = (
        float(pair[0]), float(pair[1]))
    result.metrics.update({"n_samples": float(settings.n), "n_members": float(len(codes)),
                           "latent_dim": float(codes.shape[1]),
                           "gaussian_shrinkage": gauss.shrinkage,
                           "gaussian_temperature": float(settings.temperature),
                           **({} if bandwidth is None else {"bootstrap_bandwidth": bandwidth}),
                           "resolution": float(res),
                           "spp": float(spp), **timings,
                           "wall_s": time.perf_counter() - start})
    return result
