"""How a generative run's codes are drawn, side by side: the FID of each sampler's media
against the true media's, over several seeds, and how far its samples lie from the members.

``nrt-sample`` draws new codes from the Gaussian fitted to the learned ones
(:mod:`nrt.evaluation.latent_gaussian`); this benchmark holds one finished generative stage-2
run (``--from-run``, folded first where it holds member offsets, as ``nrt-sample`` folds it,
with ``--fold-bandwidth`` as its ``fold.bandwidth``)
and compares samplers of its codes (:data:`SAMPLERS`): the Gaussian, the Gaussian at a lower
temperature, and smoothed bootstraps of the codes at several bandwidths, from the learned
codes themselves (h = 0) toward the Gaussian (h -> infinity). For each seed and sampler it
draws ``--n`` codes, decodes and renders them exactly as ``nrt-sample`` does (its functions:
the held-out cameras under the training and the held-back sky, the family's spp, render seed
1 + i for sample i) and scores FID under both skies against the members' photos, with the
real crops, the true media's renders (the reference at the same counts) and the members'
reconstructions' renders drawn once per seed and shared by every sampler. Seed 0 of the
Gaussian is what ``nrt-sample seed=0`` reports. A third reference, ``floor``: the true media
resampled to the run's medium cells (its last ``budget.rte.medium_resolutions``) and back,
rendered like the others: what the cells alone cost in FID, the least a reconstruction on
them can score. A fourth, ``unseen``: ``--n`` new media of the family's own generator (the
seeds after its members', :func:`~nrt.evaluation.sample.unseen_media`), rendered like the
others: what a sampler that draws new members exactly as the family does would score, where
``truth`` is what one that repeats the members would.

Novelty, beside FID (sigma_t MSE x100, means over the samples or members): each sample's
distance to the nearest member's reconstruction (``nearest_recon``: 0 for a sample that
repeats a learned code), against the reconstructions' distance to their nearest other one
(``recons_apart``: how far apart the decoder puts the members); each sample's distance to
the nearest member's true medium (``nearest_truth``), against the reconstructions' own error
(``recon_own``) and the true media's distance to their nearest other one (``members_apart``).
An average of the members lies close to all of them in this measure, so a small
``nearest_truth`` alone says little. The unseen media's distance to the nearest member's
true medium (``unseen_nearest_truth``) is how far a new member of the family lies. A row
per (run, fold bandwidth, sampler, seed) in ``--table``; rows already there are skipped, so
a killed benchmark continues; ``--summary`` prints the mean and spread over seeds.

    python -m benchmarks.generative_sampling --from-run DIR [--label NAME]
        [--samplers gaussian,gaussian_t0.7,bootstrap_h0.25,bootstrap_h0.5,bootstrap_scott]
        [--seeds 0,1,2] [--n 16] [--fold-bandwidth scott]
        [--table docs/data/generative_sampling.csv] [--summary]
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import append_rows, read_table, unfinished_run_error

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "docs" / "data" / "generative_sampling.csv"
SAMPLERS = {
    "gaussian": {},
    "gaussian_t0.85": {"temperature": 0.85},
    "gaussian_t0.7": {"temperature": 0.7},
    "gaussian_t0.5": {"temperature": 0.5},
    "bootstrap_h0.25": {"bandwidth": 0.25},
    "bootstrap_h0.5": {"bandwidth": 0.5},
    "bootstrap_scott": {"bandwidth": "scott"},
    "bootstrap_h1": {"bandwidth": 1.0},
}
"""Sampler name -> its ``nrt-sample`` settings (:class:`SampleSettings`' ``temperature``,
``bandwidth``; ``"scott"``: Scott's bandwidth for the run's K and d_z)."""
COLUMNS = ("train", "novel")
REFERENCES = ("_truth", "_floor", "_recon", "_unseen")
"""The true media, the true media on the run's cells, the members' reconstructions, and
new media of the family's own generator (:func:`~nrt.evaluation.sample.unseen_media`)."""
FIELDS = ("label", "run", "sampler", "temperature", "bandwidth", "seed", "n",
          *(f"fid_{col}{ref}" for col in COLUMNS for ref in ("", *REFERENCES[:3])),
          "nearest_recon", "recons_apart", "nearest_truth", "recon_own", "members_apart",
          "sample_s", "fold_bandwidth",
          *(f"fid_{col}_unseen" for col in COLUMNS), "unseen_nearest_truth")
"""The table's columns; those after ``fold_bandwidth`` came later and are empty on older
rows."""


def sigma_t_mse(a: dict, b: dict, effects: dict) -> float:
    """sigma_t MSE x100 between two media on the same grid."""
    from nrt.evaluation.evaluate import property_metrics

    return float(property_metrics(a, b, effects)["mse_sigma_t_x100"])


def nearest(media: list[dict], truths: list[dict], effects: dict,
            skip_self: bool = False) -> list[float]:
    """Each medium's sigma_t MSE x100 to the nearest of ``truths`` (not its own index with
    ``skip_self``)."""
    return [min(sigma_t_mse(m, t, effects) for j, t in enumerate(truths)
                if not (skip_self and i == j)) for i, m in enumerate(media)]


class Scorer:
    """FID of rendered media under both skies against one seed's real crops, with the
    references' renders (:data:`REFERENCES`) scored once."""

    def __init__(self, data, settings, reals: dict, references: dict):
        from nrt.evaluation.sample import make_fid, white_of

        self.fids = {}
        for col, real in reals.items():
            fid = make_fid(settings, data.cameras, white_of(real))
            fid.update(real, real=True)
            self.fids[col] = fid
        self.references = {name: {col: self.score(col, np.concatenate(stacks[col]))
                                  for col in COLUMNS}
                           for name, stacks in references.items()}

    def score(self, col: str, fake: np.ndarray) -> float:
        fid = self.fids[col]
        fid.reset(real=False)
        fid.update(torch.as_tensor(fake), real=False)
        return float(fid.compute())


@dataclass
class FamilyScoring:
    """A run's family made ready to score media as ``nrt-sample`` does: its data, FID
    settings (conf/sample.yaml's counts), the grid resolution, the family's spp, the frames
    rendered per sky and the real photos."""

    data: object
    base: object
    resolution: int
    spp: int
    frames: dict
    reals: dict

    def renders(self, media: list[dict]) -> dict[str, list[np.ndarray]]:
        """``media`` rendered as the references are (:func:`reference_renders`)."""
        from nrt.evaluation.sample import reference_renders

        n = self.base.n
        return reference_renders(media, self.data, self.frames, self.spp, 1 + n, n)

    def scorer(self, seed: int, references: dict) -> Scorer:
        """The FID of seed ``seed`` against the real photos, ``references`` scored once."""
        from nrt.evaluation.sample import SampleSettings

        return Scorer(self.data, SampleSettings(n=self.base.n, seed=seed,
                                                fid_n_crops=self.base.fid_n_crops,
                                                fid_real_views=self.base.fid_real_views),
                      self.reals, references)


def family_scoring(run: Path, n: int, fold_bandwidth: float | str | None = None
                   ) -> tuple[FamilyScoring, object]:
    """:class:`FamilyScoring` of the run folder ``run``'s family for ``n`` media per FID,
    and the run's opened folder (:func:`~nrt.evaluation.runs.open_generative_run`)."""
    from nrt.data.family import load_family
    from nrt.evaluation.runs import open_generative_run
    from nrt.evaluation.sample import (
        SampleSettings,
        load_family_data,
        real_images,
        sky_frames,
    )
    from nrt.mitsuba.variant import select_variant

    info = open_generative_run(run)
    data = load_family_data(load_family(info.family_dir), info.effects, info.scene)
    base = SampleSettings(n=n, fold_bandwidth=fold_bandwidth)  # conf/sample.yaml's FID counts
    select_variant("auto")
    return FamilyScoring(
        data=data, base=base, resolution=int(data.truths[0]["g"].shape[0]),
        spp=int((data.cameras.spec or {}).get("spp", 128)),
        frames={col: sky_frames(data.cameras, env, base.views)
                for col, env in data.skies.items()},
        reals={col: real_images(data, env, base.fid_real_views)
               for col, env in data.skies.items()}), info


@dataclass
class LoadedRun(FamilyScoring):
    """A finished generative run made ready to score (folded as ``nrt-sample`` folds it):
    :class:`FamilyScoring`, the model, the members' reconstructions (rows and grids), the
    true media on the run's cells (``floor``) and new media of the family (``unseen``)."""

    model: object = None
    recon_rows: list = None
    recon_media: list = None
    floor: list = None
    unseen: list = None


def load_run(run: Path, n: int, fold_bandwidth: float | str | None = None) -> LoadedRun:
    """:class:`LoadedRun` of the run folder ``run`` for ``n`` media per FID, folded as
    ``nrt-sample`` folds it with ``fold.bandwidth=fold_bandwidth``."""
    from nrt.data.grids import resample_grids
    from nrt.evaluation.runs import load_generative_model, read_run_folder
    from nrt.evaluation.sample import fold, reconstruction, unseen_media

    scoring, info = family_scoring(run, n, fold_bandwidth)
    data = scoring.data
    model = load_generative_model(info)
    fold(model, scoring.base)
    recon_rows, recon_media = reconstruction(model, data, scoring.resolution)
    cells = int(read_run_folder(run)[2].budget.rte.medium_resolutions[-1])
    return LoadedRun(
        **vars(scoring), model=model, recon_rows=recon_rows, recon_media=recon_media,
        floor=[resample_grids(resample_grids(t, cells), scoring.resolution)
               for t in data.truths],
        unseen=unseen_media(data, n))


def measure(run: Path, label: str, samplers: list[str], seeds: list[int], n: int,
            table: Path, fold_bandwidth: float | str | None = None) -> None:
    """The rows of ``run`` folded with ``fold_bandwidth`` for every (sampler, seed) not yet
    in ``table``."""
    from nrt.evaluation.latent_gaussian import fit_latent_gaussian
    from nrt.evaluation.sample import SampleSettings, decode, render_medium

    fold_key = "" if fold_bandwidth is None else str(fold_bandwidth)
    done = {(r["run"], r["sampler"], r["seed"], r.get("fold_bandwidth") or "")
            for r in read_table(table)}
    todo = [(s, name) for s in seeds for name in samplers
            if (str(run), name, str(s), fold_key) not in done]
    if not todo:
        return
    loaded = load_run(run, n, fold_bandwidth)
    data, model, res = loaded.data, loaded.model, loaded.resolution
    gauss = fit_latent_gaussian(model.codes.detach().float().cpu(), loaded.base.shrinkage)
    recon_media = loaded.recon_media
    recon_own = statistics.fmean(r["mse_sigma_t_x100"] for r in loaded.recon_rows)
    apart = statistics.fmean(nearest(data.truths, data.truths, data.effects, skip_self=True))
    recons_apart = statistics.fmean(nearest(recon_media, recon_media, data.effects,
                                            skip_self=True))
    references = {name: loaded.renders(media)
                  for name, media in (("truth", data.truths), ("floor", loaded.floor),
                                      ("recon", recon_media), ("unseen", loaded.unseen))}
    unseen_nearest = statistics.fmean(nearest(loaded.unseen, data.truths, data.effects))
    for seed in sorted({s for s, _ in todo}):
        scorer = loaded.scorer(seed, references)
        for name in [name for s, name in todo if s == seed]:
            start = time.perf_counter()
            settings = SampleSettings(n=n, seed=seed, **SAMPLERS[name])
            settings.check()
            bandwidth = settings.bandwidth_for(gauss.count, gauss.dim)
            drawn = gauss.sample(n, seed, settings.temperature, bandwidth)
            media = [decode(model, code, res, f"sample {i}") for i, code in enumerate(drawn)]
            renders = {col: [] for col in loaded.frames}
            for i, grids in enumerate(media):
                for col, stack in render_medium(grids, data, loaded.frames, loaded.spp,
                                                seed=1 + i).items():
                    renders[col].append(stack)
            row = {"label": label, "run": str(run), "sampler": name,
                   "temperature": settings.temperature,
                   "bandwidth": "" if bandwidth is None else f"{bandwidth:.4f}",
                   "seed": seed, "n": n}
            for col in COLUMNS:
                row[f"fid_{col}"] = f"{scorer.score(col, np.concatenate(renders[col])):.3f}"
                for ref in REFERENCES:
                    row[f"fid_{col}{ref}"] = f"{scorer.references[ref[1:]][col]:.3f}"
            novelty = {"nearest_recon": statistics.fmean(nearest(media, recon_media,
                                                                 data.effects)),
                       "recons_apart": recons_apart,
                       "nearest_truth": statistics.fmean(nearest(media, data.truths,
                                                                 data.effects)),
                       "recon_own": recon_own, "members_apart": apart,
                       "unseen_nearest_truth": unseen_nearest}
            row.update({k: f"{v:.4f}" for k, v in novelty.items()})
            row["sample_s"] = f"{time.perf_counter() - start:.1f}"
            row["fold_bandwidth"] = fold_key
            append_rows(table, FIELDS, [row])
            print(summary(read_table(table)), flush=True)


def spread(values: list[float]) -> str:
    """``mean ± sd`` (sd over the values; the mean alone for one value)."""
    if len(values) < 2:
        return f"{values[0]:.1f}"
    return f"{statistics.fmean(values):.1f} ± {statistics.stdev(values):.1f}"


def summary(rows: list[dict]) -> str:
    """Per (label, sampler): FID of the samples and of the references (true media, true
    media on the run's cells, reconstructions) under both skies, mean ± sd over its seeds,
    and the novelty distances."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["label"], r["sampler"]), []).append(r)
    lines = ["| run | sampler | seeds | FID samples: train | novel | truth: train | novel "
             "| floor: train | novel | recon: train | novel | unseen: train | novel "
             "| samples' nearest recon | recons apart | samples' nearest truth | recon own "
             "| members apart | unseen's nearest truth |",
             "|---|---|---:|" + "---:|" * 16]
    for (label, name), group in groups.items():
        def col(key: str, group=group) -> str:
            values = [float(r[key]) for r in group if r.get(key)]
            return spread(values) if values else ""
        lines.append(f"| {label} | {name} | {len(group)} | " + " | ".join(
            col(k) for k in ("fid_train", "fid_novel", "fid_train_truth", "fid_novel_truth",
                             "fid_train_floor", "fid_novel_floor",
                             "fid_train_recon", "fid_novel_recon", "fid_train_unseen",
                             "fid_novel_unseen", "nearest_recon", "recons_apart",
                             "nearest_truth", "recon_own", "members_apart",
                             "unseen_nearest_truth")) + " |")
    return "\n".join(lines)


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """``--from-run`` (a finished generative stage-2 run folder) and ``--label``."""
    parser.add_argument("--from-run", type=Path, default=None,
                        help="a finished generative stage-2 run folder")
    parser.add_argument("--label", default=None, help="the run's name in the tables")


def checked_run(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[Path, str]:
    """``--from-run`` resolved and its label (``--label``, else the folder's name); a
    missing or unfinished run is the parser's error (status 2)."""
    if args.from_run is None:
        parser.error("--from-run: name a finished generative stage-2 run folder.")
    problem = unfinished_run_error(args.from_run)
    if problem:
        parser.error(f"--from-run: {problem}")
    return args.from_run.resolve(), args.label or args.from_run.name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--samplers", default="gaussian,gaussian_t0.7,bootstrap_h0.25,"
                        "bootstrap_h0.5,bootstrap_scott")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--n", type=int, default=16, help="media to sample")
    parser.add_argument("--fold-bandwidth", default=None,
                        help="nrt-sample's fold.bandwidth: scott or a number (default: null, "
                        "the fold fits at the codes alone)")
    parser.add_argument("--table", type=Path, default=TABLE)
    parser.add_argument("--summary", action="store_true", help="print the table and stop")
    args = parser.parse_args()
    if args.summary:
        print(summary(read_table(args.table)))
        return
    run, label = checked_run(parser, args)
    samplers = args.samplers.split(",")
    unknown = [s for s in samplers if s not in SAMPLERS]
    if unknown:
        parser.error(f"--samplers: unknown {unknown}; choose from {sorted(SAMPLERS)}.")
    fold_bandwidth = args.fold_bandwidth
    if fold_bandwidth not in (None, "scott"):
        try:
            fold_bandwidth = float(fold_bandwidth)
        except ValueError:
            parser.error(f"--fold-bandwidth={fold_bandwidth}: give scott or a number >= 0.")
    measure(run, label, samplers, [int(s) for s in args.seeds.split(",")], args.n, args.table,
            fold_bandwidth)


if __name__ == "__main__":
    main()
