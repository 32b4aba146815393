"""``nrt-sample``: sample new media from a generative stage-2 run and score them.

Writes into a new folder (``<run>/sample/<timestamp>-<pid>``): ``metrics.json`` and
``metrics.md`` (FID under the training and the held-back sky, reconstruction property MSE
per member and its mean, the interpolation's MSE to its endpoints, timings),
``samples/sample<i>/`` (``medium_grids.npz``, Mitsuba ``volumes/``, the renders as EXR),
``samples_<sky>.png``, ``interpolation.png`` and ``latent_gaussian.npz``. See
:mod:`nrt.evaluation.sample`. With ``fold.steps`` > 0 (a run with member offsets; ``auto``,
the default: 2000 steps where the run holds offsets, none where it holds none) the
members' offsets are first folded into the shared decoder
(:meth:`~nrt.stages.family.SceneFamily.fold_offsets`; in memory, the run is unchanged):
samples, reconstructions and the strip then read the folded decoder.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from nrt.cli.common import run_app
from nrt.cli.eval import markdown, rows_table
from nrt.errors import NrtError

log = logging.getLogger(__name__)


def settings_of(cfg: DictConfig):
    """``conf/sample.yaml`` as :class:`~nrt.evaluation.sample.SampleSettings`."""
    from nrt.evaluation.sample import SampleSettings

    members = cfg.interpolate.members
    return SampleSettings(
        n=cfg.n, seed=cfg.seed, resolution=cfg.resolution, shrinkage=cfg.gaussian.shrinkage,
        temperature=cfg.gaussian.temperature, bandwidth=cfg.gaussian.bandwidth,
        views=cfg.render.views, spp=cfg.render.spp, export_mitsuba=cfg.export.mitsuba,
        export_exr=cfg.export.exr, fid_crop=cfg.fid.crop, fid_n_crops=cfg.fid.n_crops,
        fid_real_views=cfg.fid.real_views, fid_truth_reference=cfg.fid.truth_reference,
        fid_recon_reference=cfg.fid.recon_reference,
        fid_unseen_reference=cfg.fid.unseen_reference,
        interpolate_members=None if members is None else list(members),
        interpolate_steps=cfg.interpolate.steps, picture_max_samples=cfg.picture.max_samples,
        fold_steps=cfg.fold.steps, fold_lr=cfg.fold.lr, fold_bandwidth=cfg.fold.bandwidth)


def sample_task(cfg: DictConfig) -> dict:
    from nrt.data.family import load_family
    from nrt.evaluation.runs import load_generative_model, open_generative_run
    from nrt.evaluation.sample import (
        check_unseen,
        fold,
        load_family_data,
        make_fid,
        sample_media,
    )
    from nrt.mitsuba.variant import select_variant

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    settings = settings_of(cfg)
    settings.check()
    if not cfg.run:
        raise NrtError("nrt-sample needs run=<a generative stage-2 run folder of nrt-train> "
                       "(e.g. outputs/family/rte/<timestamp>-<pid>), and n=<media to sample>.")
    run = open_generative_run(cfg.run)
    data = load_family_data(load_family(run.family_dir), run.effects, run.scene)
    settings.check(members=len(data.family))
    if settings.fid_unseen_reference and cfg.fid.enabled:
        check_unseen(data)  # before anything is decoded or rendered
    fid = None
    if cfg.fid.enabled:  # before any decoding or render: a missing network fails in seconds
        try:
            fid = make_fid(settings, data.cameras)
        except NrtError as exc:
            raise NrtError(f"{exc} Or skip FID with fid.enabled=false.") from None
    model = load_generative_model(run, str(cfg.checkpoint))
    folded = fold(model, settings)
    select_variant(str(cfg.render.variant))
    result = sample_media(model, data, settings, out_dir, fid)
    result.metrics.update(folded)
    report = {"run": str(run.path), "family": str(data.family.root),
              "skies": data.skies, "metrics": result.metrics, "members": result.members,
              "interpolation": result.interpolation,
              "settings": OmegaConf.to_container(cfg, resolve=True)}
    (out_dir / "metrics.json").write_text(json.dumps(report, indent=1))
    text = markdown(result.metrics, result.members, f"nrt-sample of {run.path}")
    text += "\n## Interpolation (property MSE x100 to both endpoints)\n\n"
    text += "\n".join(rows_table(result.interpolation)) + "\n"
    (out_dir / "metrics.md").write_text(text)
    shown = {k: round(v, 4) for k, v in result.metrics.items()
             if k.startswith(("fid_", "recon_")) and "crops" not in k}
    log.info("Sampled %d media from %s into %s: %s", settings.n, run.path, out_dir, shown)
    return {"sample_dir": str(out_dir), "metrics": result.metrics}


def main() -> None:
    run_app(sample_task, "sample")


if __name__ == "__main__":
    main()
