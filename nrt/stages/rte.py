"""Stage 2 with the first collision split off (``nrt-train stage=rte``, the default).

The RTE is linear, so the radiance splits into the uncollided light and the light
scattered at least once, and only the second is learned:

- uncollided: ``T E(v)`` for the camera rays; inside the medium the sun-less sky's first
  scattering by MIS shadow rays (:func:`~nrt.physics.sky_light.sky_inscatter`) and the
  suns' and emitters' by shadow rays (:mod:`~nrt.physics.direct_light`): exact up to
  Monte Carlo noise, and differentiated with respect to the medium;
- scattered: a light field chosen by ``model/light_field`` (the protocol
  :class:`~nrt.modules.fields.protocols.ScatteredLightField`), by default
  :class:`~nrt.modules.fields.sh_light_field.SHGridLightField`, SH coefficients on a grid, zero on
  inflow and smooth in direction, whose in-scattering is exact for HG.

Two objectives, chosen by ``losses.objectives`` (their weights in ``losses.weights``):

- ``photo``: the training photos against the VRE of the camera rays with that
  in-scattering (:mod:`~nrt.losses.photo`); it trains the medium. The scattered light's
  coefficients enter it without gradient (their dependence on the medium is carried by
  the transport objective between steps), its ``g^l`` factors with gradient;
- ``transport``: the integral form of the RTE for the scattered light
  (:mod:`~nrt.losses.transport`); it trains the light field only.

The medium is chosen by ``model/medium`` (the protocol
:class:`~nrt.modules.fields.protocols.VoxelisedMedium`), by default
:class:`~nrt.modules.fields.voxel_medium.VoxelMedium`: the frozen EA density baked on a grid,
modulated by a grid that doubles during the run. The photo objective starts after
``light_warmup`` of the run, so the medium does not explain light the light field has not
learned yet.

Components, each in its own module: the scene source (:mod:`~nrt.stages.scene_source`),
which supplies the step's (medium, light) pairs: the single scene
(:mod:`~nrt.stages.single_scene`, with its density start, :mod:`~nrt.stages.start`) or,
with ``mode=generative``, the members of a scene family (:mod:`~nrt.stages.family`); a
light field per training sky (:mod:`~nrt.stages.sky_lights`), the uncollided light's cache
refreshed from the current media (:mod:`~nrt.stages.uncollided`) and the optional coupling
(:mod:`~nrt.stages.coupling`).

Forward mode (``stage=forward``): the medium is the dataset's ground truth and only the
transport objective runs.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import torch
from torch import nn
from torch.profiler import record_function

from nrt.errors import ConfigError
from nrt.losses.context import StepContext
from nrt.losses.objective import Objective, build_objectives, objective_class
from nrt.losses.transport import unrolled_inscatter
from nrt.modules.fields.coarse_to_fine import decaying_lr, ramp_in
from nrt.modules.fields.protocols import ScatteredLightField, VoxelisedMedium, build
from nrt.modules.fields.voxel_medium import extinction
from nrt.modules.renderers.exit import exit_radiance
from nrt.modules.renderers.volume import render_view_rays, transmitted_background
from nrt.physics.direct_light import direct_inscatter
from nrt.physics.sky_light import sky_inscatter
from nrt.stages.components import factory_config, stage_2_components
from nrt.stages.coupling import AdjointCoupling, coupling_settings
from nrt.stages.member_adam import MemberAdam, split_member_groups
from nrt.stages.radiative_transfer import RadiativeTransferStage
from nrt.stages.scene_source import SceneSource, scene_source_factory
from nrt.stages.sky_lights import SkyLights
from nrt.stages.stage import check_learning_rates
from nrt.stages.uncollided import UncollidedCache

log = logging.getLogger(__name__)


class RTEStage(RadiativeTransferStage):
    """A scattered-light field and a voxelised medium (by default the SH grid and the voxel
    medium) on the photo and transport objectives, over the (medium, light) pairs of its
    scene source (``scenes``, :mod:`~nrt.stages.scene_source`; None: the single scene). The
    light field and the medium keep the source's protocols (a family's are latent); the
    objectives and renderings take the medium and the light as arguments."""

    MANY_ENVIRONMENTS = True
    voxel_media = True

    def __init__(self, effects: dict, light_field: Callable[..., ScatteredLightField] | dict,
                 medium: Callable[..., VoxelisedMedium] | dict, density: dict,
                 weights: dict, samples: dict, lr: dict, lr_final_factor: float = 0.1,
                 light_warmup: float = 0.05, medium_rampup: float = 0.0,
                 sun: dict | None = None, eval_chunk: int = 4096,
                 property_resolution: int | None = None, coupling: dict | None = None,
                 objectives: Mapping[str, Callable[..., Objective] | dict] | None = None,
                 scenes: Callable[..., SceneSource] | dict | None = None):
        super().__init__(effects, density, sun, property_resolution)
        (make_light, make_medium, make_objectives), (light_field, medium, objectives) = \
            stage_2_components(light_field, medium, objectives)
        make_scenes = scene_source_factory(scenes)
        if scenes is not None:
            scenes = factory_config(make_scenes)
        self.save_hyperparameters()  # the components' configs
        self.automatic_optimization = False
        waits = {name: light_warmup for name, make in make_objectives.items()
                 if objective_class(make, f"losses.objectives.{name}").medium_only}
        self.objectives = build_objectives(
            weights, make_objectives, waits,
            " (the paper's four, rte/bc/obs/vre, are experiment=rte_paper)")
        if not self.learns_medium:  # forward mode: no medium to teach
            self.objectives = {name: unit for name, unit in self.objectives.items()
                               if not unit.medium_only}
        check_learning_rates(lr, "model.lr", ("light", "medium"))
        if not (isinstance(medium_rampup, (int, float)) and 0 <= medium_rampup < 1):
            raise ConfigError(f"model.medium_rampup={medium_rampup}: must be a share of the run "
                              "in [0, 1) (0: the medium's full rate at the light warm-up's end).")
        kind = make_scenes.func  # the source's class: the protocols of its light and medium
        self.light = build(make_light, kind.LIGHT_PROTOCOL, "light_field", kind.FITS,
                           effects=effects)
        self.more_lights = nn.ModuleList()  # the 2nd, 3rd ... training environment's
        self.sky_lights = SkyLights(self.light, self.more_lights, lambda: build(
            make_light, kind.LIGHT_PROTOCOL, "light_field", kind.FITS, effects=self.effects))
        if self.learns_medium:  # init=none: the modulation alone (rho = 1)
            self.medium = build(make_medium, kind.MEDIUM_PROTOCOL, "medium", kind.FITS, effects)
        self.coupling = coupling_settings(coupling)
        self.adjoint: AdjointCoupling | None = None  # with coupling.adjoint
        if self.coupling["adjoint"] and self.learns_medium:
            self.adjoint = AdjointCoupling(self.light, self.coupling["adjoint_blend"])
        self.scenes: SceneSource = make_scenes(self)
        self.uncollided = UncollidedCache(samples)

    # ----------------------------------------------------------------- set-up
    def setup(self, stage: str) -> None:
        super().setup(stage)
        if self.illuminations:
            if len(self.illuminations) > 1 and self.adjoint is not None:
                raise ConfigError("model.coupling.adjoint=true solves the adjoint of one "
                                  "environment's light; train on one (stage.environments=[0]).")
            self.sky_lights.attach(self.illuminations, self.light.bbox, self.device)
            if len(self.illuminations) > 1:
                log.info("Stage 2 trains on %d environments, a light field each",
                         len(self.illuminations))
        if self.datamodule() is not None:
            self.scenes.setup(self.datamodule())

    @property
    def env_lights(self) -> list[ScatteredLightField]:
        """The light field of each training environment, in the order of
        :attr:`illuminations` (:class:`~nrt.stages.sky_lights.SkyLights`)."""
        return self.sky_lights.fields

    def param_groups(self) -> list[dict]:
        """Adam's groups: the light field's parameters and the medium's (``model.lr``), then
        the scene source's (a family's codes)."""
        lr = self.hparams.lr
        groups = [{"params": [p for light in self.env_lights for p in light.parameters()],
                   "lr": lr["light"]}]
        if self.adjoint is not None:
            groups.append({"params": list(self.adjoint.parameters()), "lr": lr["light"]})
        if self.learns_medium:
            groups.append({"params": list(self.medium.parameters()), "lr": lr["medium"],
                           "ramps_in": True})
        return split_member_groups(groups + self.scenes.param_groups(),
                                   self.scenes.member_parameters())

    def medium_ramp(self) -> float:
        """The factor of the medium's rate (:func:`~nrt.modules.fields.coarse_to_fine.ramp_in`):
        0 during the light warm-up, then rising to 1 over ``medium_rampup`` of the run."""
        return ramp_in(self.progress(), self.hparams.light_warmup, self.hparams.medium_rampup)

    def configure_optimizers(self):
        groups = self.param_groups()
        adam = MemberAdam if any("members" in g for g in groups) else torch.optim.Adam
        opt = adam(groups)
        ramp = self.medium_ramp if self.hparams.medium_rampup > 0 else None
        sched = decaying_lr(opt, self.hparams.lr_final_factor, self.progress, ramp)
        return [opt], [{"scheduler": sched, "interval": "step"}]

    # ------------------------------------------------------------- transport
    def transport_medium(self):
        """The medium as transport reads it: composed voxels (one lookup per query) for the
        learned medium, the ground truth itself in forward mode."""
        return self.medium.voxels() if self.learns_medium else self.medium

    def step_context(self, scenes) -> StepContext:
        """The base's context with the photos' in-scattering (:meth:`photo_source`) and the
        learned voxel media (the source's ``fresh_voxels``; none in forward mode)."""
        context = super().step_context(scenes)
        context.photo_source = self.photo_source
        context.voxels = self.scenes.fresh_voxels if self.learns_medium else None
        return context

    def photo_source(self, medium, light: ScatteredLightField):
        """:meth:`inscatter` of ``light`` as the photos read it (:meth:`photo_light`)."""
        read, coefficients_grad = self.photo_light(light)
        return self.inscatter(medium, read, coefficients_grad)

    def inscatter(self, medium, light: ScatteredLightField, coefficients_grad: bool = False):
        """In-scattering of all light for the camera rays' VRE: the first scattering of the
        sky and the known lights of ``light``'s environment (with gradients to ``medium``)
        plus the scattered light's (``light``) exact SH in-scattering (``g^l`` with gradient,
        the coefficients only with ``coefficients_grad``)."""
        s = self.hparams.samples
        sigma_t = extinction(medium)
        sky = self.sky_lights.illumination_of(light)

        def source(x, w, props):
            total = sky_inscatter(x, w, props.g, sigma_t, medium.bbox, sky.rest,
                                  sky.sampler, int(s["sky_env_directions"]),
                                  int(s["sky_phase_directions"]), int(s["shadow_steps"]))
            if len(sky.lights):
                total = total + direct_inscatter(x, w, props.g, sky.lights, sigma_t,
                                                 medium.bbox, int(s["shadow_steps"]), jitter=True)
            total = total + light.inscatter(x, w, props.g, trainable=coefficients_grad)
            n_dirs = int(self.coupling["unrolled_directions"])
            if n_dirs > 0 and torch.is_grad_enabled():
                total = total + unrolled_inscatter(
                    light, medium, x, w, props.g, n_dirs,
                    int(self.coupling["unrolled_samples"]))
            return total
        return source

    def _update_resolution(self) -> None:
        if self.learns_medium and \
                self.medium.follow_schedule(self.progress(), self.optimizers().optimizer):
            log.info("Medium modulation resampled to %d^3 cells at step %d",
                     self.medium.resolution, self.global_step)

    # --------------------------------------------------------------- training
    def photo_light(self, light: ScatteredLightField) -> tuple[ScatteredLightField, bool]:
        """``light`` as the photo objective reads it, and whether its coefficients take
        gradient there: as it is, without; with the adjoint on, the stage's own light read
        through a leaf whose gradient becomes the adjoint's source
        (:class:`~nrt.stages.coupling.AdjointCoupling`)."""
        if light is not self.light or self.adjoint is None:
            return light, False
        return self.adjoint.photo_light(light), True

    def refresh_uncollided(self, scenes) -> None:
        """Refresh the uncollided cache of the light of each (medium, light) pair of
        ``scenes`` in its medium (without gradient) that the scene source says is due
        (``uncollided_due``, on :class:`~nrt.stages.uncollided.UncollidedCache`'s
        schedule), logging the seconds."""
        start = time.perf_counter()
        with record_function("nrt/uncollided"):  # a profiler scope (benchmarks.profile_step)
            due = self.scenes.uncollided_due(self.uncollided, self.global_step)
            for first in (True, False):
                group = [scenes[i] for i, new in due if new == first]
                if group:
                    self.uncollided.refresh_all(group, self.sky_lights.illumination_of, first)
            if due:
                self.uncollided.fresh = True
        self.log("time/step_uncollided_s", time.perf_counter() - start)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        opt = self.optimizers()
        self._update_resolution()
        scenes = self.scenes.pairs(batch)
        self.refresh_uncollided(scenes)
        opt.zero_grad(set_to_none=True)
        scene = self.scenes.scene_of(batch)
        if scene is not None:
            batch = {**batch, "scene": scene}
        total = self.backward_priors(self.backward_objectives(batch,
                                                              self.step_context(scenes)))
        self.scenes.backward_media(self.manual_backward)
        grad = self.adjoint.take_gradient() if self.adjoint is not None else None
        if grad is not None:  # one environment, one pair (setup refuses more)
            self.adjoint_step(scenes[0][0], grad)
        for name, value in self.scenes.step_metrics().items():
            self.log(f"train/{name}", value)
        if self.learns_medium:
            self.log("train/medium_resolution", float(self.medium.resolution))
        with record_function("nrt/optimizer"):
            opt.step()
            self.lr_schedulers().step()
        return torch.as_tensor(total)

    def backward_priors(self, total: torch.Tensor) -> torch.Tensor:
        """Backpropagate the scene source's priors while a medium objective is active (beside
        their data term: alone, Adam would scale their tiny gradient up to full steps),
        logging each; returns ``total`` (the objectives' weighted loss) plus those that
        acted, detached."""
        priors = self.scenes.priors()
        acting = priors and any(self.objectives[name].medium_only
                                for name in self.active_weights())
        for name, prior in priors.items():
            if acting:
                self.manual_backward(prior)
                total = total + prior.detach()
            self.log(f"train/{name}", prior.detach())
        return total

    def adjoint_step(self, medium, grad: torch.Tensor) -> None:
        """One step of the adjoint coupling from the photo loss's gradient ``grad`` to the
        scattered light's coefficients (:meth:`AdjointCoupling.backward`), logged."""
        start = time.perf_counter()
        s = self.hparams.samples
        with record_function("nrt/adjoint"):
            loss = self.adjoint.backward(self.light, medium, self.medium.voxels, grad,
                                         int(s["transport_points"]), int(s["transport_samples"]),
                                         self.manual_backward)
        self.log("train/loss_adjoint", loss)
        self.log("time/step_adjoint_s", time.perf_counter() - start)

    # ------------------------------------------------------------- validation
    def predict_view(self, batch: dict) -> dict[str, torch.Tensor]:
        """:meth:`predict_pixels` of a held-out view through the scene source's pair for it
        (its environment's light; a family member's medium and light)."""
        with torch.no_grad():
            medium, light = self.scenes.view_pair(batch)
            return self.render_pixels(batch["origins"], batch["dirs"], batch["background"],
                                      medium, light)

    def predict_pixels(self, origins: torch.Tensor, dirs: torch.Tensor,
                       background: torch.Tensor) -> dict[str, torch.Tensor]:
        """Two predictions of ``L(o, -v)`` (R, 3) for view rays, chunked, without graph:
        ``vre`` (the photo objective's rendering, strata centres) and ``exit`` (``T E(v)``
        plus the scattered light where the ray leaves the box: the light field alone)."""
        with torch.no_grad():
            return self.render_pixels(origins, dirs, background, self.transport_medium(),
                                      self.light)

    @torch.no_grad()
    def render_pixels(self, origins: torch.Tensor, dirs: torch.Tensor, background: torch.Tensor,
                      medium, light: ScatteredLightField) -> dict[str, torch.Tensor]:
        """:meth:`predict_pixels` through ``medium`` with ``light``."""
        s, chunk = self.hparams.samples, self.hparams.eval_chunk
        out: dict[str, list] = {"vre": [], "exit": []}
        source = self.inscatter(medium, light)
        for i in range(0, len(origins), chunk):
            o, d, bg = origins[i:i + chunk], dirs[i:i + chunk], background[i:i + chunk]
            out["vre"].append(render_view_rays(medium, o, d, bg, int(s["vre_samples"]),
                                               source, jitter=False))
            scattered = exit_radiance(light, o, d, torch.zeros_like(bg))
            out["exit"].append(transmitted_background(medium, o, d, bg,
                                                      int(s["vre_samples"])) + scattered)
        return {k: torch.cat(v) for k, v in out.items()}

    # ------------------------------------------------------- grids and export
    def property_grids(self, resolution: int) -> dict[str, torch.Tensor] | None:
        """The scene source's: the learned medium of a single scene (None in forward mode),
        None for a family (one medium per member)."""
        return self.scenes.property_grids(resolution)

    def member_property_grids(self, member: int, resolution: int
                              ) -> dict[str, torch.Tensor] | None:
        return self.scenes.member_property_grids(member, resolution)

    def export(self, run_dir: str | Path) -> dict[str, str]:
        """The base's ``medium_grids.npz`` (of a single scene) and what the scene source
        writes (a family's members and codes), at ``property_resolution``."""
        return {**super().export(run_dir),
                **self.scenes.export(Path(run_dir), self.hparams.property_resolution)}

    # ------------------------------------------------------------------ resume
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """Also record the scene source's settings learned at the start of the run (a
        family's EA field and members) with its config, so that the checkpoint rebuilds it."""
        super().on_save_checkpoint(checkpoint)
        if self.hparams.scenes is not None and "hyper_parameters" in checkpoint:
            checkpoint["hyper_parameters"]["scenes"] = {**self.hparams.scenes,
                                                        **self.scenes.settings()}

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """The scene source's start comes with the state (no EA field needed); the medium
        resizes its grid to the checkpoint's itself
        (:class:`~nrt.modules.fields.voxel_medium.VoxelMedium`); the light fields of more
        environments than one are built to receive theirs. The uncollided caches come
        with the state too: a resumed run refreshes them on their schedule, as the run left
        alone does, not at once."""
        super().on_load_checkpoint(checkpoint)
        self.scenes.on_load_checkpoint(checkpoint)
        self.uncollided.fresh = checkpoint.get("global_step", 0) > 0
        more = {key.split(".")[1] for key in checkpoint["state_dict"]
                if key.startswith("more_lights.")}
        self.sky_lights.grow(1 + len(more), self.device)
