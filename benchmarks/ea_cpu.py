"""Stage 1 (EA) at the ``cpu`` preset for a fixed wall-clock budget.

Prints held-out PSNR (log tonemap) of the learned EA model and of the background alone,
the correlation and relative L2 error between learned density and ground-truth sigma_t
(luminance) on the ground-truth grid, and training throughput in rays per second.

    python benchmarks/ea_cpu.py --seconds 300 [--scene default] [override ...]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import lightning as L
import torch
from omegaconf import OmegaConf

from benchmarks.common import compose_train
from nrt.cli.common import tune_allocator
from nrt.data.render import ensure_dataset
from nrt.metrics import density_agreement, psnr
from nrt.modules.renderers.emission_absorption import render_rays
from nrt.physics.tonemap import luminance


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=300.0, help="training wall-clock budget")
    parser.add_argument("--scene", default="default")
    parser.add_argument("overrides", nargs="*", help="extra Hydra overrides")
    args = parser.parse_args()
    tune_allocator()
    cfg = compose_train([f"scene={args.scene}", "preset=cpu", "stage=ea", *args.overrides])
    L.seed_everything(cfg.seed)
    folder = ensure_dataset(OmegaConf.to_container(cfg.scene, resolve=True), cfg.paths.data_dir)
    import hydra

    dm = hydra.utils.instantiate(cfg.data, dataset_dir=str(folder), val_views=None)
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    with tempfile.TemporaryDirectory() as tmp:
        trainer = L.Trainer(accelerator="cpu", max_steps=-1, max_epochs=-1,
                            max_time={"seconds": args.seconds}, logger=False,
                            enable_checkpointing=False, enable_progress_bar=False,
                            limit_val_batches=0, num_sanity_val_steps=0,
                            inference_mode=False, default_root_dir=tmp)
        start = time.perf_counter()
        trainer.fit(model, datamodule=dm)
        train_s = time.perf_counter() - start
    steps = trainer.global_step
    rays_per_s = steps * cfg.data.batch_size / train_s
    psnrs, base = [], []
    with torch.no_grad():
        for batch in dm.val_dataloader():
            pred = render_rays(model.field, batch["origins"], batch["dirs"], batch["background"],
                               model.hparams.samples_per_ray, jitter=False, chunk=8192)
            psnrs.append(float(psnr(pred, batch["rgb"])))
            base.append(float(psnr(batch["background"], batch["rgb"])))
    gt = dm.ground_truth
    sigma_t = luminance(gt["sigma_a"] + gt["sigma_s"])
    agree = density_agreement(model.density_grid(sigma_t.shape[0]), sigma_t)
    print(f"scene={args.scene} preset=cpu budget={args.seconds:.0f}s steps={steps} "
          f"rays/batch={cfg.data.batch_size} samples/ray={cfg.model.samples_per_ray}")
    print(f"held-out PSNR (log tonemap, {len(psnrs)} views): EA {sum(psnrs) / len(psnrs):.2f} dB"
          f" | background only {sum(base) / len(base):.2f} dB")
    print(f"density vs ground-truth sigma_t (luminance): corr {float(agree['corr']):.3f}, "
          f"relative L2 error {float(agree['rel_err']):.3f}")
    print(f"throughput: {rays_per_s:,.0f} rays/s ({train_s / max(steps, 1) * 1e3:.1f} ms/step)")


if __name__ == "__main__":
    main()
