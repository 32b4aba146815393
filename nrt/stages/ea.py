"""Stage 1: the emission-absorption LightningModule (``nrt-train stage=ea``).

Renders camera rays through a density field (``model/density_field=<name>``; by default the
hash-grid :class:`~nrt.modules.fields.ea_field.EAField`) inside the medium
box with stratified jittered samples, alpha-composites them in front of the known
background ``E(v)`` and fits the photos (MSE after the log tonemap: HDR pixels would
otherwise let the sun's glints dominate). Validation renders held-out views and
compares the learned density with the ground-truth extinction where available.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch.profiler import record_function

from nrt.errors import ConfigError, NrtError
from nrt.files import atomic_write, writing
from nrt.metrics import density_agreement
from nrt.modules.fields.protocols import DensityField, build
from nrt.modules.renderers.emission_absorption import render_rays
from nrt.physics.tonemap import log_tonemap, luminance
from nrt.physics.volume import at_cell_centres
from nrt.stages.checkpoints import check_checkpoint_file, read_checkpoint
from nrt.stages.components import as_factory, factory_config
from nrt.stages.stage import Stage, check_learning_rates
from nrt.tensorboard import log_image

DENSITY_GRID_FILE = "density_grid.npz"

PHOTOMETRIC_LOSSES = {
    "log_mse": lambda pred, ref: torch.mean((log_tonemap(pred) - log_tonemap(ref)) ** 2),
    "mse": lambda pred, ref: torch.mean((pred - ref) ** 2),
}


FITS = ("Stage 1 (stage=ea) renders a density field with a colour: a module with "
        "density(x, latent) and field(x, d, latent) -> (density, rgb), as "
        "model/density_field=hash_grid builds")

def density_field_config(hparams: dict) -> dict:
    """The density field's config (``_target_``, ``_partial_``, keywords) that a stage-1
    checkpoint's hyperparameters record as ``density_field``."""
    return dict(hparams["density_field"])


def density_field_factory(component: Callable | dict) -> functools.partial:
    """The density field's factory from what a stage receives: Hydra's partial or a
    recorded config."""
    return as_factory(component, "density_field")


def build_density_field(factory: Callable[..., DensityField], latent_dim: int | None = None
                        ) -> DensityField:
    """``factory()``, or ``factory(latent_dim=d_z)`` for a field conditioned on codes,
    checked against :class:`~nrt.modules.fields.protocols.DensityField` (a misfit is a
    ``ConfigError`` naming ``model/density_field``)."""
    codes = {} if latent_dim is None else {"latent_dim": latent_dim}
    return build(factory, DensityField, "density_field", FITS, **codes)


def latent_dim_of(hparams: dict) -> int:
    """d_z of a stage-1 checkpoint's field (``latent_dim``); 0 for a single scene."""
    return int(hparams.get("latent_dim") or 0)


class EAModule(Stage):
    """Fits a density field (:class:`~nrt.modules.fields.protocols.DensityField`; by default
    the hash-grid :class:`~nrt.modules.fields.ea_field.EAField`) to the training photos of
    a scene. It learns a density, not a medium (no property grids; its export is
    ``density_grid.npz``).

    ``density_field`` is the factory Hydra builds from ``model/density_field`` (a checkpoint
    holds its config); the stage calls it with ``latent_dim`` when that is set (the codes'
    d_z in generative mode; None for one scene)."""

    def __init__(self, density_field: Callable[..., DensityField] | dict,
                 samples_per_ray: int = 64, loss: str = "log_mse", lr: float = 1e-2,
                 eps: float = 1e-15, weight_decay: float = 1e-6, eval_chunk: int = 8192,
                 density_resolution: int | None = None, latent_dim: int | None = None):
        super().__init__()
        make_field = density_field_factory(density_field)
        # the hyperparameters record the field's config: a checkpoint pickles no code
        density_field = factory_config(make_field)
        self.save_hyperparameters()
        if loss not in PHOTOMETRIC_LOSSES:
            raise ConfigError(f"losses.photometric must be one of {sorted(PHOTOMETRIC_LOSSES)}, "
                              f"got '{loss}'.")
        check_learning_rates(lr, "model.lr")
        self.photometric = PHOTOMETRIC_LOSSES[loss]
        self.field = build_density_field(make_field, latent_dim)

    def setup(self, stage: str) -> None:
        dm = self.datamodule()
        if dm is not None:
            self.field.bbox.copy_(dm.bbox.to(self.field.bbox))

    def compile_hot_code(self) -> None:
        """The density field (hash-grid encoding and MLPs), compiled in place: its state
        dict's keys stay as they are."""
        self.field.compile(dynamic=True)  # the rays that hit the box vary in number

    def configure_optimizers(self):
        """Adam over the field's parameters, weight decay on all but its ``encoding``'s (if it
        has one: a hash grid's table is not decayed)."""
        encoding = getattr(self.field, "encoding", None)
        enc = list(encoding.parameters()) if encoding is not None else []
        enc_ids = {id(p) for p in enc}
        rest = [p for p in self.field.parameters() if id(p) not in enc_ids]
        return torch.optim.Adam(
            [{"params": enc}, {"params": rest, "weight_decay": self.hparams.weight_decay}],
            lr=self.hparams.lr, eps=self.hparams.eps, betas=(0.9, 0.99))

    def ray_latents(self, batch: dict) -> torch.Tensor | None:
        """Each ray's latent code (R, d_z) for a conditioned field; None for one scene."""
        return None

    def render(self, batch: dict, jitter: bool, chunk: int | None = None) -> torch.Tensor:
        """The EA radiance (R, 3) of a batch's rays (:func:`render_rays`)."""
        return render_rays(self.field, batch["origins"], batch["dirs"], batch["background"],
                           self.hparams.samples_per_ray, jitter=jitter, chunk=chunk,
                           latent=self.ray_latents(batch))

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        with record_function("nrt/objective/photometric/forward"):  # benchmarks.profile_step
            loss = self.photometric(self.render(batch, jitter=True), batch["rgb"])
        self.log("train/loss", loss, prog_bar=True)
        return loss

    def backward(self, loss: torch.Tensor, *args, **kwargs) -> None:
        """Lightning's backward of the step's loss, in the profiler scope
        ``nrt/objective/photometric/backward`` (benchmarks.profile_step)."""
        with record_function("nrt/objective/photometric/backward"):
            super().backward(loss, *args, **kwargs)

    def validation_step(self, batch: dict, batch_idx: int) -> dict[str, torch.Tensor]:
        """Render one held-out view; the output carries ``member`` when the batch does."""
        h, w = batch["shape"]
        pred = self.render(batch, jitter=False, chunk=self.hparams.eval_chunk)
        ref = batch["rgb"]
        member = batch.get("member")
        for key, value in self.view_baselines(batch).items():
            self.log(f"val/{key}", value, batch_size=1)
        if batch_idx == 0:
            log_image(self, "val/render_vs_truth",
                      torch.cat((pred.reshape(h, w, 3), ref.reshape(h, w, 3)), 1))
        out = {"image": pred.reshape(h, w, 3), "reference": ref.reshape(h, w, 3)}
        if member is not None:
            out["member"] = int(member)
        return out

    @torch.no_grad()
    def density_grid(self, resolution: int, latent: torch.Tensor | None = None
                     ) -> torch.Tensor:
        """Learned density (R, R, R) at the box's cell centres, indexed [z, y, x]; ``latent``
        (d_z,) is the code of a conditioned field."""
        return at_cell_centres(lambda pts: self.field.density(pts, latent), resolution,
                               self.field.bbox, self.hparams.eval_chunk * 8)

    def score_density(self, gt: dict[str, torch.Tensor], latent: torch.Tensor | None = None
                      ) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """Agreement (``corr``, ``rel_err``) of the learned density with the luminance of the
        true sigma_t on the ground truth's grid, and the middle z-slices learned | true
        (H, 2W, 3) scaled by the true maximum, for TensorBoard."""
        sigma_t = luminance(gt["sigma_a"] + gt["sigma_s"]).to(self.device)
        learned = self.density_grid(sigma_t.shape[0], latent)
        mid = sigma_t.shape[0] // 2
        panel = torch.cat((learned[mid], sigma_t[mid]), 1) / sigma_t.max().clamp_min(1e-8)
        return (density_agreement(learned, sigma_t),
                panel.clamp(0, 1).unsqueeze(-1).expand(-1, -1, 3))

    def on_validation_epoch_end(self) -> None:
        gt = self.ground_truth()
        if gt is None:
            return
        agree, panel = self.score_density(gt)
        self.log("val/density_corr", agree["corr"])
        self.log("val/density_rel_err", agree["rel_err"])
        log_image(self, "val/density_slice_vs_truth", panel)

    def write_density_grid(self, path: Path, resolution: int,
                           latent: torch.Tensor | None = None) -> str:
        """Write ``density_grid.npz`` (``density`` [z, y, x] per unit length, ``bbox``) of
        the field (under ``latent``) at ``resolution`` cells per axis to ``path``, replaced
        atomically."""
        density = self.density_grid(resolution, latent).cpu().numpy()
        with writing("the density grid", path):
            path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path, "the density grid") as f:
            np.savez_compressed(f, density=density, bbox=self.field.bbox.cpu().numpy())
        return str(path)

    def export(self, run_dir: str | Path) -> dict[str, str]:
        """Write ``density_grid.npz`` at ``density_resolution`` (default: the ground truth's,
        else 64) into ``run_dir``."""
        res = self.grid_resolution(self.hparams.density_resolution, 64)
        return {"density_grid": self.write_density_grid(Path(run_dir) / DENSITY_GRID_FILE,
                                                        res)}


def load_ea_field(ckpt_path: str | None, map_location: str | torch.device = "cpu"
                  ) -> DensityField:
    """The trained density field of a stage-1 checkpoint (for the density queries of the stages
    that start from it); a missing file is a user error naming the fix."""
    check_checkpoint_file(ckpt_path, "nrt-train stage=ea scene=<same scene>")
    saved = read_checkpoint(ckpt_path)
    if latent_dim_of(saved.get("hyper_parameters", {})):
        raise NrtError(f"init.ea_ckpt='{ckpt_path}' is a generative EA run over a scene family "
                       "(mode=generative): its field needs a member's latent code. Train stage "
                       "2 on the family (nrt-train stage=rte mode=generative scene=family "
                       "init.ea_ckpt=<it>), or start from a single-scene EA run (nrt-train "
                       "stage=ea scene=<scene>).")
    module = EAModule.load_from_checkpoint(ckpt_path, map_location=map_location)
    return module.field


