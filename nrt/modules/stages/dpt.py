"""Baseline: differentiable volumetric path tracing of property grids (``stage=dpt``).

Optimises voxel grids of extinction ``sigma_t`` (RGB, or one grey channel) and albedo
(RGB), and of g when the scene's phase varies (through the ``nrt_hg_grid`` plugin), so
that Mitsuba's ``prbvolpath`` renders of the grids match the photos, with full multiple
scattering. Mitsuba estimates the gradients by **differentiable delta tracking** (path
replay backpropagation), not the differential ratio tracking of the paper's baseline.

- Start: the EA density of the same scene (stage 1) at the coarsest grid into every
  channel of sigma_t, a neutral albedo (``init_albedo``), g = 0; or (``init=grids``)
  property grids in the format every stage exports (``init.grids``, a run's
  ``medium_grids.npz``), resampled to the coarsest grid: the path tracer refines another
  method's medium with the full multiple-scattering gradient.
- Each step renders one random training view, under its own environment (one Mitsuba
  scene per environment of ``stage.environments``), at ``spp`` with gradients; the loss is the
  MSE after the log tonemap (as stage 1 and the evaluation compare images), taken in
  Dr.Jit (:meth:`nrt.mitsuba.render.ViewRenderer.log_image_loss`); ``dr.backward`` gives
  the grid gradients, which become the ``.grad`` of torch parameters (non-finite entries
  counted and zeroed), and torch's Adam steps, its rate decaying exponentially to
  ``lr_final_factor`` of ``lr`` over the run. Values are
  clamped after each step: ``0 <= sigma_t <= max_sigma_t``, albedo in [0, 1], |g| <= 0.95.
- Coarse to fine: the grids double (trilinear, cell-centred) at the fractions
  ``upsample_at`` of the run (of its steps, or of ``budget_s`` when that comes first)
  until ``resolutions[-1]``; Adam's moments restart at each doubling. With ``ea_detail``
  sigma_t also gets the EA density's detail of the finer grid added (what the coarser
  grid could not hold): worth it when the first grid is too coarse for the medium (the
  ``tiny`` preset's 8^3), not when the EA density's own fine detail is noisier than its
  coarse shape (``cpu``: EA at 64^3 is further from the truth than EA at 16^3).
- For ``phase=hg`` the single g is not optimised: ``phase_g``, or (null) the ground
  truth's sigma_s-weighted mean when the dataset has one (an oracle the method lacks),
  else 0. Isotropic scenes have no g.

The grids are torch parameters, so checkpoints, resume (at the resolution reached) and
the non-finite guard work as for every stage; exports use the ground truth's layout.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from nrt.cameras import fov_x_deg
from nrt.data.grids import (
    MEDIUM_GRIDS_FILE,
    load_property_grids,
    resample_grids,
    save_property_grids,
)
from nrt.errors import ConfigError, NrtError
from nrt.modules.fields.coarse_to_fine import (
    check_schedule,
    decaying_lr,
    resample_parameter,
    resolution_at,
)
from nrt.modules.fields.voxel_medium import bake
from nrt.modules.stages.stage import Stage, check_learning_rates
from nrt.physics.phase import G_MAX, shared_g
from nrt.physics.volume import resample_cells
from nrt.tensorboard import log_image

log = logging.getLogger(__name__)

MITSUBA_KEYS = {"sigma_t": "sigma_t.data", "albedo": "albedo.data", "g": "g.data"}


def check_start(density: dict, ea_detail: bool) -> None:
    """Refuse a start other than ``init=ea`` or ``init=grids`` with an existing
    ``init.grids`` file (and the EA detail, which needs an EA density, with grids)."""
    source = density.get("source")
    if source == "ea":
        return
    if source != "grids":
        raise NrtError("stage=dpt starts from the EA density (init=ea) or from property "
                       f"grids (init=grids init.grids=<medium_grids.npz>); init.source="
                       f"'{source}' is not supported.")
    path = density.get("grids")
    if not path or not Path(str(path)).expanduser().is_file():
        raise ConfigError(f"init.grids='{path}': init=grids starts stage=dpt from a property-"
                          "grid file (sigma_a, sigma_s, g; a run's medium_grids.npz); give "
                          "an existing file, or use init=ea for the EA density.")
    if ea_detail:
        raise ConfigError("budget.dpt.ea_detail=true adds the EA density's detail at each "
                          "doubling, but init=grids has no EA density: set it false.")


class DPTModule(Stage):
    """Grids of sigma_t, albedo (and g) fitted by differentiable path tracing."""

    def __init__(self, effects: dict, density: dict, resolutions: list[int],
                 upsample_at: list[float], spp: int = 8, val_spp: int = 32,
                 lr: float = 0.02, lr_final_factor: float = 0.1, init_albedo: float = 0.8,
                 max_sigma_t: float = 100.0,
                 phase_g: float | None = None, property_resolution: int | None = None,
                 ea_detail: bool = False, seed: int = 0):
        super().__init__(effects)
        self.save_hyperparameters()
        self.automatic_optimization = False
        check_schedule(resolutions, upsample_at, "budget.dpt.resolutions / upsample_at")
        check_learning_rates(lr, "losses.lr")
        check_start(density, ea_detail)
        res, channels = int(resolutions[0]), 3 if effects.get("chromatic", True) else 1
        self.sigma_t = nn.Parameter(torch.ones(res, res, res, channels))
        self.albedo = nn.Parameter(torch.full((res, res, res, 3), float(init_albedo)))
        self.g = nn.Parameter(torch.zeros(res, res, res, 1)) \
            if effects["phase"] == "varying_hg" else None
        self.register_buffer("bbox", torch.tensor([[-1.0] * 3, [1.0] * 3]))
        self._renderers: dict[int, object] = {}  # a Mitsuba scene per environment, built once
        self._frames = None
        self._fixed_g = 0.0
        self._started = False  # grids set (from the EA density, or by a checkpoint)
        self._ea = {}  # the EA field (kept out of the module's parameters and checkpoints)
        self.nonfinite_grads = 0  # of the last image_loss, zeroed before Adam

    # ----------------------------------------------------------------- set-up
    def grids(self) -> dict[str, nn.Parameter]:
        """The optimised grids by name (``g`` only when g varies)."""
        out = {"sigma_t": self.sigma_t, "albedo": self.albedo}
        if self.g is not None:
            out["g"] = self.g
        return out

    @property
    def learns_g(self) -> bool:
        """Only a g field is learned; a fixed g (phase=hg) is not scored."""
        return self.effects["phase"] == "varying_hg"

    def setup(self, stage: str) -> None:
        dm = self.datamodule()
        if dm is None:
            return
        self.bbox.copy_(dm.bbox)
        if not self._started:  # a resume overwrites it later; a trained module keeps its grids
            self._init_grids()
        gt = dm.ground_truth
        if self.effects["phase"] == "hg" and not self._started:
            if self.hparams.phase_g is not None:
                self._fixed_g = float(self.hparams.phase_g)
            elif gt is not None:
                self._fixed_g = shared_g(gt["sigma_s"], gt["g"])
            log.info("dpt keeps the HG g fixed at %.4f (%s)", self._fixed_g,
                     "model.phase_g" if self.hparams.phase_g is not None else
                     "the ground truth's: an oracle" if gt is not None else "default")
        self.use_views(dm.train_data, {index: env.radiance.cpu().numpy()
                                       for index, env in dm.training_environments().items()},
                       dm.val_data)
        self._started = True

    def use_views(self, frames, envmaps: dict[int, np.ndarray], val_data=None) -> None:
        """The photos to fit (``images`` (N, H, W, 3), OpenGL ``c2w`` (N, 4, 4),
        ``intrinsics`` and ``env_index`` (N,), like :class:`nrt.data.dataset.SceneDataset`),
        each lit by its environment map in ``envmaps`` (environment index -> (H, W, 3)), and
        the held-out views for validation (lit by the same maps)."""
        self._frames, self._envmaps, self._val_data = frames, envmaps, val_data
        self._renderers = {}

    @torch.no_grad()
    def _init_grids(self) -> None:
        """The start: the EA density into sigma_t (``init=ea``), or every grid from
        ``init.grids`` (``init=grids``), at the current resolution."""
        res, density = self.sigma_t.shape[0], self.hparams.density
        if density["source"] == "ea":
            self.sigma_t.copy_(self._ea_density(res).expand_as(self.sigma_t))
            log.info("dpt starts from the EA density of %s at %d^3 cells",
                     density["ea_ckpt"], res)
            return
        grids = load_property_grids(density["grids"])
        grids = resample_grids(grids, res)  # the file's cells over the same box
        sigma_t = grids["sigma_a"] + grids["sigma_s"]
        albedo = grids["sigma_s"] / sigma_t.clamp_min(1e-12)
        sigma_t = sigma_t if self.sigma_t.shape[-1] == 3 else sigma_t.mean(-1, keepdim=True)
        self.sigma_t.copy_(sigma_t.clamp(0, self.hparams.max_sigma_t))
        self.albedo.copy_(albedo.clamp(0, 1))
        if self.g is not None:
            self.g.copy_(grids["g"].clamp(-G_MAX, G_MAX).unsqueeze(-1))
        log.info("dpt starts from the property grids %s at %d^3 cells", density["grids"], res)

    @torch.no_grad()
    def _ea_density(self, res: int) -> torch.Tensor:
        """The EA density (clamped like sigma_t) at the cell centres of res^3 cells,
        (R, R, R, 1) on the parameters' device."""
        from nrt.modules.stages.ea import load_ea_field

        if "field" not in self._ea:
            self._ea["field"] = load_ea_field(self.hparams.density["ea_ckpt"])
        field = self._ea["field"]
        return bake(field.density, res, self.bbox.cpu()).clamp_max(
            self.hparams.max_sigma_t).to(self.sigma_t.device)

    def configure_optimizers(self):
        opt = torch.optim.Adam(self.parameters(), lr=self.hparams.lr)
        sched = decaying_lr(opt, self.hparams.lr_final_factor, self.progress)
        return [opt], [{"scheduler": sched, "interval": "step"}]

    # -------------------------------------------------------------- Mitsuba
    def property_arrays(self) -> dict[str, np.ndarray]:
        """The grids as the ground truth's arrays: sigma_a, sigma_s (R, R, R, 3), g."""
        sigma_t = self.sigma_t.detach().cpu().expand(*self.albedo.shape[:3], 3)
        albedo = self.albedo.detach().cpu()
        g = self.g.detach().cpu()[..., 0] if self.g is not None else torch.full(
            sigma_t.shape[:3], self._fixed_g)
        return {"sigma_a": ((1 - albedo) * sigma_t).numpy(), "sigma_s": (albedo * sigma_t).numpy(),
                "g": g.numpy()}

    def renderer(self, env: int):
        """The Mitsuba scene (``prbvolpath``) of the current grids under environment
        ``env`` (an index of :meth:`use_views`'s maps), built once."""
        if env not in self._renderers:
            from nrt.mitsuba.render import ViewRenderer
            from nrt.mitsuba.scene import scene_dict
            from nrt.mitsuba.variant import select_variant

            mi = select_variant("auto")
            intr = self._frames.intrinsics
            spec = {"bbox": self.bbox.cpu().tolist(), "effects": self.effects}
            renderer = ViewRenderer(mi, scene_dict(
                mi, spec, self.property_arrays(), self._envmaps[env], intr.width, intr.height,
                fov_x_deg(intr, "The training cameras"), self.hparams.spp,
                integrator="prbvolpath"))
            self._keys = renderer.medium_keys(
                {name: suffix for name, suffix in MITSUBA_KEYS.items() if name in self.grids()})
            self._renderers[env] = renderer
        return self._renderers[env]

    def _grid_values(self) -> dict[str, np.ndarray]:
        """The torch grids as Mitsuba's parameters (scene key -> array; the same keys in
        every environment's scene)."""
        return {key: self.grids()[name].detach().cpu().contiguous().numpy()
                for name, key in self._keys.items()}

    def render_view(self, c2w: torch.Tensor, spp: int, seed: int, env: int) -> torch.Tensor:
        """A forward render (H, W, 3) of the current grids from an OpenGL camera under
        environment ``env``."""
        renderer = self.renderer(env)
        renderer.set_parameters(self._grid_values())
        return torch.from_numpy(renderer.render(c2w.cpu().numpy(), spp, seed))

    # --------------------------------------------------------------- training
    def _resolution_now(self) -> int:
        """Coarse to fine over the run's course (steps, or seconds of a ``budget_s``)."""
        return resolution_at(self.progress(), self.hparams.resolutions,
                             self.hparams.upsample_at)

    @torch.no_grad()
    def _resize(self, res: int) -> None:
        """Trilinear, cell-centred resampling of every grid to res^3, Adam's state for them
        restarted (:mod:`nrt.modules.fields.coarse_to_fine`; moments resampled with the grid left
        the steps 8x too small after a doubling). With ``ea_detail`` sigma_t also gets back
        the EA density's detail that the coarse grid could not hold (EA at res^3 minus EA at
        the old resolution, upsampled): a doubling without optimisation in between yields
        the EA density at res^3 itself."""
        opt = self.optimizers().optimizer
        old = self.sigma_t.shape[0]
        for p in self.grids().values():
            resample_parameter(p, opt, res)
        if self.hparams.ea_detail:
            detail = self._ea_density(res) - resample_cells(self._ea_density(old), res)
            self.sigma_t.data = (self.sigma_t.data + detail).clamp(0, self.hparams.max_sigma_t)
        log.info("dpt grids doubled to %d^3 at step %d", res, self.global_step)

    def image_loss(self, frame: int, seed: int) -> float:
        """Render training view ``frame`` of the current grids with gradients (``spp``,
        Mitsuba's ``seed``), compare it with its photo (MSE after the log1p tonemap) and
        store the loss's gradient as the ``.grad`` of every grid (non-finite entries
        zeroed). Returns the loss."""
        loss, grads = self.renderer(int(self._frames.env_index[frame])).log_image_loss(
            self._frames.c2w[frame].cpu().numpy(), self._frames.images[frame].cpu().numpy(),
            self._grid_values(), int(self.hparams.spp), int(seed))
        self.nonfinite_grads = 0
        for name, key in self._keys.items():
            grad = grads[key]
            bad = ~np.isfinite(grad)
            if bad.any():  # counted, then zeroed (NaN must never reach Adam's moments)
                self.nonfinite_grads += int(bad.sum())
                grad = np.where(bad, 0.0, grad).astype(np.float32)
            param = self.grids()[name]
            param.grad = torch.from_numpy(grad.reshape(param.shape)).to(param.device)
        return loss

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        res = self._resolution_now()
        if res != self.sigma_t.shape[0]:
            self._resize(res)
        start = time.perf_counter()
        gen = torch.Generator().manual_seed(self.hparams.seed * 1_000_003 + self.global_step)
        frame = int(torch.randint(len(self._frames), (1,), generator=gen))
        opt = self.optimizers()
        opt.zero_grad(set_to_none=True)
        value = self.image_loss(frame, seed=self.global_step)
        opt.step()
        self.lr_schedulers().step()
        self._clamp()
        self.log("train/loss", value, prog_bar=True)
        self.log("time/step_render_s", time.perf_counter() - start)
        self.log("train/grid_resolution", float(res))
        self.log("train/nonfinite_render_grads", float(self.nonfinite_grads))
        return torch.tensor(value)

    @torch.no_grad()
    def _clamp(self) -> None:
        self.sigma_t.clamp_(0.0, float(self.hparams.max_sigma_t))
        self.albedo.clamp_(0.0, 1.0)
        if self.g is not None:
            self.g.clamp_(-G_MAX, G_MAX)

    # ------------------------------------------------------------- validation
    def validation_step(self, batch: dict, batch_idx: int) -> dict[str, torch.Tensor]:
        h, w = batch["shape"]
        view = int(batch["view"])
        pred = self.render_view(self._val_data.c2w[view], int(self.hparams.val_spp),
                                seed=1_000_003 + view, env=int(self._val_data.env_index[view]))
        ref = batch["rgb"].reshape(h, w, 3).cpu()
        if batch_idx == 0:
            log_image(self, "val/render_vs_truth", torch.cat((pred, ref), 1))
        return {"image": pred, "reference": ref}

    def property_grids(self, resolution: int) -> dict[str, torch.Tensor]:
        """The grids resampled to R^3 cells in the ground truth's layout."""
        arrays = {k: torch.from_numpy(np.ascontiguousarray(v))
                  for k, v in self.property_arrays().items()}
        return resample_grids(arrays, resolution)

    def medium_bbox(self) -> torch.Tensor:
        return self.bbox

    # -------------------------------------------------------------- resume
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["dpt_fixed_g"] = self._fixed_g

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Resize the grids to the checkpoint's resolution before its state is loaded, and
        restore the fixed g of a ``phase=hg`` scene."""
        self._fixed_g = float(checkpoint.get("dpt_fixed_g", self._fixed_g))
        self._started = True
        state = checkpoint.get("state_dict", {})
        with torch.no_grad():
            for name, p in self.grids().items():
                if name in state and state[name].shape != p.shape:
                    p.data = torch.zeros_like(state[name])

    def teardown(self, stage: str) -> None:
        """Drop the Mitsuba scene (Dr.Jit 3.9 can fail to compile a kernel while older
        scenes of the same plugins are still alive in the process)."""
        self._renderers = {}

    def export(self, run_dir: str | Path) -> dict[str, str]:
        """``medium_grids.npz`` at ``property_resolution`` (default: the ground truth's,
        else the final grid's)."""
        res = self.grid_resolution(self.hparams.property_resolution, self.sigma_t.shape[0])
        path = save_property_grids(Path(run_dir) / MEDIUM_GRIDS_FILE,
                                   self.property_grids(res), self.bbox)
        return {"medium_grids": str(path)}

