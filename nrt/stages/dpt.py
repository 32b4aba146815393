"""Baseline: differentiable volumetric path tracing of property grids (``stage=dpt``).

Optimises voxel grids of extinction ``sigma_t`` (RGB, or one grey channel), albedo (RGB)
and g (one shared g for ``phase=hg``, a g field for ``varying_hg``, through the
``nrt_hg_grid`` plugin) so that Mitsuba's ``prbvolpath`` renders of the grids match the
photos, with full multiple scattering. Mitsuba estimates the gradients by
**differentiable delta tracking** (path replay backpropagation), not the differential
ratio tracking of the paper's baseline.

- Grids: :class:`~nrt.modules.fields.path_traced_grids.PathTracedGrids` under
  ``parametrization`` (``linear``, ``log``, or ``modulated`` like stage 2's medium).
- Start: the EA density of the same scene (stage 1) baked on ``start_resolution``^3
  cells (stage 2 bakes it on ``budget.rte.density_resolution``^3: the same start), into
  every channel of sigma_t, a neutral albedo (``init_albedo``), g = 0; or (``init=grids``)
  property grids in the format every stage exports (``init.grids``, a run's
  ``medium_grids.npz``).
- g: learned (``phase_g: null``), as stage 2 learns it; or fixed at ``phase_g``.
- Each step renders ``views_per_step`` random training views, each under its own
  environment (one Mitsuba scene per environment of ``stage.environments``), at ``spp``
  with gradients (at ``spp_final`` once the grids reach their final resolution, when
  given: cheap steps while the grids are coarse, a cleaner gradient on the finest); the
  image loss (``loss``: ``l2_log``, the MSE after the log1p tonemap as stage 1 and the
  evaluation compare images; ``l1_log``; ``l2_relative``) is taken in
  Dr.Jit (:meth:`nrt.mitsuba.render.ViewRenderer.image_loss`) and averaged over the views;
  ``dr.backward`` gives the gradients of the rendered arrays, which torch back-propagates
  through the parametrisation to the parameters (non-finite entries counted and zeroed),
  together with the optional extinction prior (``extinction_prior`` times the mean
  extinction, as stage 2's). Adam steps (g's grid at ``lr_g_factor`` times the others'
  rate); its rate decays exponentially to
  ``lr_final_factor`` of ``lr`` over the run and is multiplied by ``lr_drop_factor`` at
  each fraction of ``lr_drops`` (the differential-ratio-tracking code halves it at 75, 85
  and 95 %).
- Coarse to fine: the grids double (trilinear, cell-centred) at the fractions
  ``upsample_at`` of the run (of its steps, or of ``budget_s`` when that comes first)
  until ``resolutions[-1]``; Adam's moments restart at each doubling.

The grids are torch parameters, so checkpoints, resume (at the resolution reached) and
the non-finite guard work as for every stage; exports use the ground truth's layout.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from torch.profiler import record_function

from nrt.cameras import fov_x_deg
from nrt.data.grids import (
    MEDIUM_GRIDS_FILE,
    load_property_grids,
    resample_grids,
    save_property_grids,
)
from nrt.errors import ConfigError, NrtError
from nrt.modules.fields.coarse_to_fine import check_schedule, resolution_at
from nrt.modules.fields.path_traced_grids import PathTracedGrids
from nrt.modules.fields.voxel_medium import bake
from nrt.stages.stage import Stage, check_learning_rates
from nrt.tensorboard import log_image

log = logging.getLogger(__name__)

MITSUBA_KEYS = {"sigma_t": "sigma_t.data", "albedo": "albedo.data", "g": "g.data"}
LOSSES = ("l2_log", "l1_log", "l2_relative")


def check_start(density: dict) -> None:
    """Refuse a start other than ``init=ea`` or ``init=grids`` with an existing
    ``init.grids`` file."""
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


def check_settings(loss: str, views_per_step: int, lr_drops, lr_drop_factor: float,
                   extinction_prior: float, spp: int, spp_final: int | None) -> None:
    """Refuse settings no run can use, naming the key."""
    if loss not in LOSSES:
        raise ConfigError(f"losses.image='{loss}': the baseline's image loss is one of "
                          f"{list(LOSSES)}.")
    if int(views_per_step) < 1:
        raise ConfigError(f"budget.dpt.views_per_step={views_per_step}: render at least one "
                          "view a step.")
    for key, value in (("spp", spp), ("spp_final", spp_final)):
        if value is not None and int(value) < 1:
            raise ConfigError(f"budget.dpt.{key}={value}: at least one sample per pixel"
                              + (" (null: spp's)." if key == "spp_final" else "."))
    if any(not 0 < f < 1 for f in lr_drops) or list(lr_drops) != sorted(lr_drops):
        raise ConfigError(f"losses.lr_drops={list(lr_drops)}: increasing fractions of the run "
                          "in (0, 1).")
    if not 0 < lr_drop_factor <= 1:
        raise ConfigError(f"losses.lr_drop_factor={lr_drop_factor}: a factor in (0, 1].")
    if extinction_prior < 0:
        raise ConfigError(f"losses.extinction_prior={extinction_prior}: a weight >= 0.")


class DPTModule(Stage):
    """Grids of sigma_t, albedo and g fitted by differentiable path tracing."""

    def __init__(self, effects: dict, density: dict, resolutions: list[int],
                 upsample_at: list[float], spp: int = 8, spp_final: int | None = None,
                 val_spp: int = 32,
                 lr: float = 0.02, lr_g_factor: float = 1.0, lr_final_factor: float = 0.1,
                 lr_drops: list[float] | tuple = (), lr_drop_factor: float = 0.5,
                 views_per_step: int = 1, loss: str = "l2_log",
                 parametrization: str = "linear", start_resolution: int | None = None,
                 init_albedo: float = 0.8, max_sigma_t: float = 100.0,
                 phase_g: float | None = None, extinction_prior: float = 0.0,
                 property_resolution: int | None = None, seed: int = 0):
        super().__init__(effects)
        self.save_hyperparameters()
        self.automatic_optimization = False
        check_schedule(resolutions, upsample_at, "budget.dpt.resolutions / upsample_at")
        check_learning_rates(lr, "losses.lr")
        check_learning_rates(lr * lr_g_factor, "losses.lr_g_factor (times losses.lr)")
        check_start(density)
        check_settings(loss, views_per_step, list(lr_drops), lr_drop_factor, extinction_prior,
                       spp, spp_final)
        phase = effects["phase"]
        g_kind = "none" if phase == "isotropic" else "fixed" if phase_g is not None else \
            "field" if phase == "varying_hg" else "shared"
        self.medium = PathTracedGrids(3 if effects.get("chromatic", True) else 1,
                                      int(resolutions[0]), g_kind, parametrization,
                                      start_resolution or int(resolutions[0]), max_sigma_t)
        self.medium.fixed_g = float(phase_g) if phase_g is not None else 0.0
        self.register_buffer("bbox", torch.tensor([[-1.0] * 3, [1.0] * 3]))
        self._renderers: dict[int, object] = {}  # a Mitsuba scene per environment, built once
        self._frames = None
        self._started = False  # grids set (from the start, or by a checkpoint)
        self.nonfinite_grads = 0  # of the last image_loss, zeroed before Adam

    # ----------------------------------------------------------------- set-up
    def grids(self) -> dict[str, torch.nn.Parameter]:
        """The optimised grids by name (``g`` only when g is learned)."""
        return self.medium.parameters_by_name()

    @property
    def learns_g(self) -> bool:
        """g is learned (and scored) unless the scene is isotropic or ``phase_g`` fixes it."""
        return self.medium.g is not None

    def setup(self, stage: str) -> None:
        dm = self.datamodule()
        if dm is None:
            return
        self.bbox.copy_(dm.bbox)
        if not self._started:  # a resume overwrites it later; a trained module keeps its grids
            self._init_grids()
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

    def _start_resolution(self) -> int:
        return int(self.hparams.start_resolution or self.hparams.resolutions[0])

    @torch.no_grad()
    def _init_grids(self) -> None:
        """The start: the EA density baked on ``start_resolution``^3 cells (``init=ea``), or
        every grid from ``init.grids`` resampled to them (``init=grids``)."""
        res, density = self._start_resolution(), self.hparams.density
        if density["source"] == "ea":
            from nrt.stages.ea import load_ea_field

            field = load_ea_field(density["ea_ckpt"])
            sigma_t = bake(field.density, res, self.bbox.cpu())
            self.medium.start(sigma_t, torch.full((res, res, res, 3),
                                                  float(self.hparams.init_albedo)))
            log.info("dpt starts from the EA density of %s baked on %d^3 cells",
                     density["ea_ckpt"], res)
        else:
            grids = resample_grids(load_property_grids(density["grids"]), res)
            sigma_t = grids["sigma_a"] + grids["sigma_s"]
            if self.medium.channels == 1:
                sigma_t = sigma_t.mean(-1, keepdim=True)
            albedo = grids["sigma_s"] / (grids["sigma_a"] + grids["sigma_s"]).clamp_min(1e-12)
            self.medium.start(sigma_t, albedo, grids["g"] if self.learns_g else None)
            log.info("dpt starts from the property grids %s on %d^3 cells", density["grids"],
                     res)
        self.medium.to(self.bbox.device)

    def configure_optimizers(self):
        lr, grids = float(self.hparams.lr), self.grids()
        g = grids.pop("g", None)
        groups = [{"params": list(grids.values()), "lr": lr}]
        if g is not None:
            groups.append({"params": [g], "lr": lr * float(self.hparams.lr_g_factor)})
        opt = torch.optim.Adam(groups)
        drops, drop = list(self.hparams.lr_drops), float(self.hparams.lr_drop_factor)
        final = float(self.hparams.lr_final_factor)

        def factor(_: int) -> float:
            progress = self.progress()
            return final ** progress * drop ** sum(progress >= f for f in drops)

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return [opt], [{"scheduler": sched, "interval": "step"}]

    # -------------------------------------------------------------- Mitsuba
    def property_arrays(self) -> dict[str, np.ndarray]:
        """The grids as the ground truth's arrays: sigma_a, sigma_s (R, R, R, 3), g."""
        return {k: v.cpu().numpy() for k, v in self.medium.property_arrays().items()}

    def renderer(self, env: int):
        """The Mitsuba scene (``prbvolpath``) of the current grids under environment
        ``env`` (an index of :meth:`use_views`'s maps), built once. A learned g is read
        through the ``nrt_hg_grid`` phase (a one-cell grid for one shared g)."""
        if env not in self._renderers:
            with record_function("nrt/render_setup"):  # a profiler scope (profile_step)
                self._renderers[env] = self._build_renderer(env)
        return self._renderers[env]

    def _build_renderer(self, env: int):
        """The Mitsuba scene of :meth:`renderer` under environment ``env``, newly built
        (and the scene keys of the grids, :attr:`_keys`)."""
        from nrt.mitsuba.render import ViewRenderer
        from nrt.mitsuba.scene import scene_dict
        from nrt.mitsuba.variant import select_variant

        mi = select_variant("auto")
        intr = self._frames.intrinsics
        arrays = self.property_arrays()
        effects = dict(self.effects)
        if self.learns_g:
            effects["phase"] = "varying_hg"
            arrays["g"] = self.medium.values()["g"].detach().cpu().numpy()[..., 0]
        spec = {"bbox": self.bbox.cpu().tolist(), "effects": effects}
        renderer = ViewRenderer(mi, scene_dict(
            mi, spec, arrays, self._envmaps[env], intr.width, intr.height,
            fov_x_deg(intr, "The training cameras"), self.hparams.spp,
            integrator="prbvolpath"))
        self._keys = renderer.medium_keys(
            {name: suffix for name, suffix in MITSUBA_KEYS.items() if name in self.grids()})
        return renderer

    def _mitsuba_values(self, values: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
        """Arrays of :meth:`PathTracedGrids.values` as Mitsuba's parameters (scene key ->
        array; the same keys in every environment's scene)."""
        return {key: values[name].detach().cpu().contiguous().numpy()
                for name, key in self._keys.items()}

    def render_view(self, c2w: torch.Tensor, spp: int, seed: int, env: int) -> torch.Tensor:
        """A forward render (H, W, 3) of the current grids from an OpenGL camera under
        environment ``env``."""
        renderer = self.renderer(env)
        with torch.no_grad():
            renderer.set_parameters(self._mitsuba_values(self.medium.values()))
        return torch.from_numpy(renderer.render(c2w.cpu().numpy(), spp, seed))

    # --------------------------------------------------------------- training
    def _resolution_now(self) -> int:
        """Coarse to fine over the run's course (steps, or seconds of a ``budget_s``)."""
        return resolution_at(self.progress(), self.hparams.resolutions,
                             self.hparams.upsample_at)

    def training_spp(self) -> int:
        """Samples per pixel of a training render now: ``spp_final`` (when given) once the
        grids are at their final resolution, else ``spp``."""
        final = self.hparams.get("spp_final")
        if final is not None and self.medium.resolution == int(self.hparams.resolutions[-1]):
            return int(final)
        return int(self.hparams.spp)

    def image_loss(self, frames: int | list[int], seed: int) -> float:
        """Render training views ``frames`` of the current grids with gradients
        (:meth:`training_spp`,
        Mitsuba's ``seed`` plus the view's position in the list), compare each with its
        photo (``loss``) and store the gradient of their mean, plus the extinction prior's,
        as the ``.grad`` of every grid (non-finite entries of Mitsuba's gradients counted
        and zeroed). Returns the mean image loss."""
        frames = [frames] if isinstance(frames, int) else list(frames)
        values = self.medium.values()
        for p in self.grids().values():
            p.grad = None
        self.nonfinite_grads, total = 0, 0.0
        grads: dict[str, np.ndarray] = {}
        arrays = None  # Mitsuba's keys are known once a renderer is built
        for k, frame in enumerate(frames):
            renderer = self.renderer(int(self._frames.env_index[frame]))
            arrays = arrays or self._mitsuba_values(values)
            value, view_grads = renderer.image_loss(
                self._frames.c2w[frame].cpu().numpy(), self._frames.images[frame].cpu().numpy(),
                arrays, self.training_spp(), int(seed) + k, self.hparams.loss)
            total += value
            for key, grad in view_grads.items():
                grads[key] = grads[key] + grad if key in grads else grad
        surrogate = torch.zeros(())
        for name, key in self._keys.items():
            grad = grads[key] / len(frames)
            bad = ~np.isfinite(grad)
            if bad.any():  # counted, then zeroed (NaN must never reach Adam's moments)
                self.nonfinite_grads += int(bad.sum())
                grad = np.where(bad, 0.0, grad).astype(np.float32)
            target = values[name]
            surrogate = surrogate + (target * torch.from_numpy(grad.reshape(target.shape)).to(
                target.device)).sum()
        if self.hparams.extinction_prior > 0:
            surrogate = surrogate + self.hparams.extinction_prior * values["sigma_t"].mean()
        surrogate.backward()
        return total / len(frames)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        res = self._resolution_now()
        if res != self.medium.resolution:
            self.medium.resize(res, self.optimizers().optimizer)
            log.info("dpt grids doubled to %d^3 at step %d", res, self.global_step)
        start = time.perf_counter()
        gen = torch.Generator().manual_seed(self.hparams.seed * 1_000_003 + self.global_step)
        views = int(self.hparams.views_per_step)
        frames = torch.randperm(len(self._frames), generator=gen)[:views].tolist() \
            if views <= len(self._frames) else \
            torch.randint(len(self._frames), (views,), generator=gen).tolist()
        opt = self.optimizers()
        # profiler scopes (benchmarks.profile_step): the torch side of the image loss (the
        # grids' parametrisation and its backward), inside it Mitsuba's (nrt/mitsuba/render.py)
        with record_function("nrt/parametrisation"):
            value = self.image_loss(frames, seed=self.global_step * views)
        with record_function("nrt/optimizer"):
            opt.step()
            self.lr_schedulers().step()
            self.medium.clamp_()
        self.log("train/loss", value, prog_bar=True)
        self.log("time/step_render_s", time.perf_counter() - start)
        self.log("train/grid_resolution", float(res))
        self.log("train/nonfinite_render_grads", float(self.nonfinite_grads))
        return torch.tensor(value)

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
        return resample_grids(self.medium.property_arrays(), resolution)

    def medium_bbox(self) -> torch.Tensor:
        return self.bbox

    # -------------------------------------------------------------- resume
    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Resize the grids to the checkpoint's resolution before its state is loaded."""
        super().on_load_checkpoint(checkpoint)
        self._started = True
        self.medium.resize_to_state(checkpoint.get("state_dict", {}), "medium.")

    def teardown(self, stage: str) -> None:
        """Drop the Mitsuba scene (Dr.Jit 3.9 can fail to compile a kernel while older
        scenes of the same plugins are still alive in the process)."""
        self._renderers = {}

    def export(self, run_dir: str | Path) -> dict[str, str]:
        """``medium_grids.npz`` at ``property_resolution`` (default: the ground truth's,
        else the final grid's)."""
        res = self.grid_resolution(self.hparams.property_resolution,
                                   self.medium.values()["sigma_t"].shape[0])
        path = save_property_grids(Path(run_dir) / MEDIUM_GRIDS_FILE,
                                   self.property_grids(res), self.bbox)
        return {"medium_grids": str(path)}
