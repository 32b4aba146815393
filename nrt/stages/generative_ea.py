"""Stage 1 in generative mode (``nrt-train stage=ea mode=generative scene=family``): an
auto-decoder in the DeepSDF manner (Park et al. 2019) over the K members of a scene family.

Member k has an optimisable latent code ``z_k`` (d_z values, drawn from
``N(0, latent_init_std^2)`` at the start) under an L2 prior: the loss is the photometric
loss plus ``latent_prior_weight * mean_k |z_k|^2``. The density field is conditioned on z
(built with ``latent_dim = d_z``; :class:`~nrt.modules.fields.ea_field.EAField`: its
hash-grid features multiplied by ``1 + M(z)``), and each ray is rendered with its member's
code, so a batch that mixes members trains the shared field and every code in it. The codes are the
module's parameter ``codes`` (K, d_z), so checkpoints hold them and a resumed run
continues them; they have their own optimiser group (``latent_lr``, no weight decay: the
prior is their regulariser).

Validation scores each member's held-out views (``val/psnr_member<k>``, ``val/ssim_member<k>``,
by :class:`~nrt.callbacks.HeldOutImageMetrics`) and its density against its own ground
truth (``val/density_corr_member<k>``, ``val/density_rel_err_member<k>``), and their means
(``val/psnr``, ``val/density_corr``, ...). The export writes each member's density grid in
the single-scene layout (``members/<name>/density_grid.npz``) and the codes
(``latents.npz``: ``codes`` (K, d_z), ``names``, ``seeds``), to which a Gaussian can be
fitted.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from nrt.errors import ConfigError, DatasetError, NrtError
from nrt.files import atomic_write
from nrt.modules.fields.protocols import DensityField
from nrt.run_dirs import read_run_info
from nrt.stages.checkpoints import check_checkpoint_file, read_checkpoint
from nrt.stages.components import factory_config
from nrt.stages.ea import (
    DENSITY_GRID_FILE,
    EAModule,
    density_field_config,
    density_field_factory,
    latent_dim_of,
)
from nrt.stages.stage import check_learning_rates
from nrt.tensorboard import log_image

LATENTS_FILE = "latents.npz"
MEMBERS_DIR = "members"


class GenerativeEAModule(EAModule):
    """An :class:`EAModule` whose density field is conditioned on one latent code per
    family member (``members`` = K, codes of ``latent_dim`` = d_z >= 1 values, passed to the
    field's factory). Batches carry each ray's ``member``; the rest of the arguments are
    :class:`EAModule`'s."""

    def __init__(self, members: int, latent_dim: int,
                 density_field: Callable[..., DensityField] | dict,
                 latent_init_std: float = 0.01, latent_prior_weight: float = 1e-4,
                 latent_lr: float = 1e-2, **kwargs):
        # the hyperparameters record the field's config: a checkpoint pickles no code
        density_field = factory_config(density_field_factory(density_field))
        if isinstance(members, bool) or not isinstance(members, int) or members < 1:
            raise ConfigError(f"model.members={members}: the number of family members K "
                              "must be a whole number >= 1 (scene.family.members).")
        if isinstance(latent_dim, bool) or not isinstance(latent_dim, int) or latent_dim < 1:
            raise ConfigError(f"model.latent_dim={latent_dim}: the generative mode needs latent "
                              "codes of at least one dimension (mode.latent.dim).")
        check_learning_rates(latent_lr, "model.latent_lr")
        super().__init__(density_field=density_field, latent_dim=latent_dim, **kwargs)
        self.codes = nn.Parameter(torch.randn(members, latent_dim) * latent_init_std)

    # ------------------------------------------------------------------ training
    def configure_optimizers(self):
        optimizer = super().configure_optimizers()  # the field's parameters only
        optimizer.add_param_group({"params": [self.codes], "lr": self.hparams.latent_lr,
                                   "weight_decay": 0.0})
        return optimizer

    def ray_latents(self, batch: dict) -> torch.Tensor:
        """The code (R, d_z) of each ray's member: ``member`` is (R,) in training batches,
        one index (the view's member) in validation batches."""
        member = batch["member"]
        if isinstance(member, int):
            return self.codes[member].expand(batch["origins"].shape[0], -1)
        return self.codes[member.to(self.codes.device)]

    def latent_prior(self) -> torch.Tensor:
        """``latent_prior_weight * mean_k |z_k|^2``: the codes' Gaussian prior, as a loss."""
        return self.hparams.latent_prior_weight * self.codes.square().sum(-1).mean()

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        photometric = self.photometric(self.render(batch, jitter=True), batch["rgb"])
        prior = self.latent_prior()
        loss = photometric + prior
        self.log("train/loss", loss, prog_bar=True)
        self.log("train/photometric", photometric)
        self.log("train/latent_prior", prior)
        self.log("train/latent_norm", self.codes.detach().norm(dim=-1).mean())
        return loss

    # ---------------------------------------------------------------- validation
    def setup(self, stage: str) -> None:
        super().setup(stage)
        dm = self.datamodule()
        if dm is not None and dm.num_members != self.codes.shape[0]:
            raise DatasetError(f"Family '{dm.dataset_dir}' has {dm.num_members} members but "
                               f"the model holds {self.codes.shape[0]} codes "
                               "(scene.family.members); render and train the same family.")

    def member_ground_truths(self) -> list[dict[str, torch.Tensor] | None]:
        """Each member's ground-truth grids (None where a member has none); [] outside a
        trainer."""
        dm = self.datamodule()
        return dm.member_ground_truths if dm is not None else []

    def on_validation_epoch_end(self) -> None:
        scores, panels = {"corr": [], "rel_err": []}, []
        for k, gt in enumerate(self.member_ground_truths()):
            if gt is None:
                continue
            agree, panel = self.score_density(gt, self.codes[k])
            for key, value in agree.items():
                self.log(f"val/density_{key}_member{k}", value)
                scores[key].append(value)
            panels.append(panel)
        if not panels:
            return
        for key, values in scores.items():
            self.log(f"val/density_{key}", torch.stack(values).mean())
        log_image(self, "val/density_slice_vs_truth", torch.cat(panels, 0))  # a row a member

    # -------------------------------------------------------------------- export
    def export(self, run_dir: str | Path) -> dict[str, str]:
        """Write ``members/<name>/density_grid.npz`` for every member (at
        ``density_resolution``, default the ground truth's, else 64) and ``latents.npz``
        (``codes`` (K, d_z), ``names`` and ``seeds`` of the members) into ``run_dir``."""
        run_dir = Path(run_dir)
        dm = self.datamodule()
        family = dm.family if dm is not None else None
        members = family.members if family is not None else []
        names = [m.name for m in members] or [f"member{k}" for k in range(len(self.codes))]
        seeds = [m.seed for m in members] or list(range(len(self.codes)))
        res = self.grid_resolution(self.hparams.density_resolution, 64,
                                   self.member_ground_truths())
        exports = {f"density_grid_{name}": self.write_density_grid(
            run_dir / MEMBERS_DIR / name / DENSITY_GRID_FILE, res, self.codes[k])
            for k, name in enumerate(names)}
        exports["latents"] = save_latents(run_dir, self.codes, names, seeds)
        return exports


def save_latents(run_dir: str | Path, codes: torch.Tensor, names: list[str],
                 seeds: list[int]) -> str:
    """Write ``latents.npz`` (``codes`` (K, d_z), the members' ``names`` and ``seeds``)
    into ``run_dir``; returns its path."""
    path = Path(run_dir) / LATENTS_FILE
    with atomic_write(path, "the latent codes") as f:
        np.savez(f, codes=codes.detach().cpu().numpy(), names=np.array(names),
                 seeds=np.array(seeds))
    return str(path)


def load_generative_ea(ckpt_path: str | None) -> tuple[dict, DensityField, torch.Tensor,
                                                       list[dict] | None]:
    """What generative stage 2 takes from a generative EA checkpoint: the density field's
    config (:func:`~nrt.stages.ea.density_field_config`; its factory takes
    ``latent_dim``), the field (on the CPU), the codes (K, d_z) and the members (``index``,
    ``seed``, ``name``, as the run's ``run.json`` records them; None where it has none). A
    missing file, or a single-scene EA run, is a user error naming the fix."""
    check_checkpoint_file(ckpt_path, "nrt-train stage=ea mode=generative scene=family")
    saved = read_checkpoint(ckpt_path)
    hparams = saved.get("hyper_parameters", {})
    if not latent_dim_of(hparams) or "codes" not in saved.get("state_dict", {}):
        raise NrtError(f"init.ea_ckpt='{ckpt_path}' is a single-scene EA run; stage 2 in "
                       "generative mode starts from a generative EA run over the same family "
                       "(nrt-train stage=ea mode=generative scene=family, then pass its "
                       "checkpoints/last.ckpt).")
    module = GenerativeEAModule.load_from_checkpoint(ckpt_path, map_location="cpu")
    codes = module.codes.detach().clone()
    info = read_run_info(Path(ckpt_path).resolve().parent.parent)
    return density_field_config(hparams), module.field, codes, info.get("members")
