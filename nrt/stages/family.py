"""The scene family of generative stage 2 (``nrt-train stage=rte mode=generative
scene=family init.ea_ckpt=<generative EA run>``): the split stage of :mod:`nrt.stages.rte`
trained on the K members of a family through :class:`SceneFamily`, its scene source
(:mod:`nrt.stages.scene_source`), which conditions each member's medium and light on one
latent code (the auto-decoder of :mod:`nrt.stages.generative_ea`, continued).

- **Codes.** ``codes`` (K, d_z) start from the generative EA run's and stay optimisable
  (their own Adam group, ``latent_lr``, under the L2 prior ``latent_prior_weight * mean_k
  |z_k|^2``). The prior acts only while the photo objective does: alone (during the light
  field's warm-up) Adam would scale its tiny gradient up to steps of ``latent_lr`` and pull
  every code to the origin, erasing the members' differences (measured: 100 such steps
  made the four tiny members' media alike).
- **Medium** (:class:`~nrt.modules.fields.voxel_medium.LatentVoxelMedium`): member k's density is
  the frozen EA field evaluated under z_k on the voxels (the field's hash features at the
  cell centres are computed once; its modulation by z and its density MLP run every step,
  so the density follows the code, with gradient); its modulation (sigma_t exponents and
  albedo logits, ``parametrization=extinction``) is an MLP of shared grid features of x
  (coarse to fine) concatenated with z_k.
- **Light** (:class:`~nrt.modules.fields.sh_light_field.LatentSHGridLightField`): the scattered
  light's SH coefficients are an MLP of shared grid features of x concatenated with z_k;
  each member keeps its own cache of the uncollided light, all under the family's one
  training sky (shared suns and sun-less sky).
- **Objectives**, as in the single-scene split stage: the photo objective trains the medium
  and the codes (each ray rendered through its member's medium); the transport objective
  trains the light field, which reads the codes without gradient, at collocation points
  that each carry a member index (split evenly over the members). Each objective is the
  mean over all rays or points of the family.
- **Noise on the codes** (``code_noise`` h > 0, off by default): each step decodes a
  member's medium (density and modulation) at ``z_k + h s * eps`` (eps ~ N(0, I), a fresh
  draw per member and step; s the codes' standard deviation over the members, per
  dimension, without gradient), its light at z_k: the photos of member k then train the
  decoders on codes around z_k, as a sampler's smoothed bootstrap draws them, not at z_k
  alone.
- **Members a step.** By default a step's rays mix all K members, and the step decodes K
  media and lights. With ``data.members_per_step=M`` each step draws M members (the same on
  every rank) and its rays, collocation points, priors and uncollided refreshes concern
  those M only: a step decodes M, each member's uncollided light is refreshed every
  ``uncollided_every`` of its own steps, and a code absent from a step gets no prior step.

Validation scores each member's held-out views (``val/psnr_member<k>``, by
:class:`~nrt.callbacks.HeldOutImageMetrics`) and its medium against its own ground truth
(``val/mse_<property>_x100_member<k>``, by :class:`~nrt.callbacks.PropertyMetrics`), and
their means. For other tools (``nrt-sample``) the family decodes a medium from any code
(:meth:`SceneFamily.property_grids_for`); the export writes every member's
``members/<name>/medium_grids.npz`` and the codes (``latents.npz``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import nn
from torch.profiler import record_function

from nrt.data.grids import MEDIUM_GRIDS_FILE, save_property_grids
from nrt.errors import ConfigError, DatasetError
from nrt.modules.fields.latent_grid import CodeKernel
from nrt.modules.fields.medium import property_grids
from nrt.modules.fields.protocols import LatentScatteredLightField, LatentVoxelisedMedium
from nrt.physics.volume import at_cell_centres
from nrt.stages.components import factory_config
from nrt.stages.ea import build_density_field, density_field_factory
from nrt.stages.generative_ea import MEMBERS_DIR, load_generative_ea, save_latents
from nrt.stages.stage import check_learning_rates, grid_resolution

if TYPE_CHECKING:
    from nrt.stages.rte import RTEStage

FITS = ("Generative stage 2 (stage=rte mode=generative) takes the latent light field and "
        "medium that conf/mode_stage/generative_rte.yaml sets")


class SceneFamily(nn.Module):
    """The ``members`` (K) of a family as the ``stage``'s (medium, light) pairs, conditioned
    on codes of ``latent_dim`` (d_z) values: member k's medium is the stage's latent medium
    over the frozen EA field's density, both under z_k; its light is the stage's latent
    light field under z_k. ``ea_field`` (the EA run's density-field config) and
    ``member_info`` (``name``, ``seed`` of each member) come from the EA checkpoint (the
    stage's ``density.ea_ckpt``) when the run starts, and from the stage's checkpoint when
    it is loaded (:meth:`settings`). The module holds the frozen field ``ea`` and the codes;
    the light field and the medium stay the stage's (its state holds them)."""

    LIGHT_PROTOCOL = LatentScatteredLightField
    MEDIUM_PROTOCOL = LatentVoxelisedMedium
    FITS = FITS

    def __init__(self, stage: RTEStage, members: int, latent_dim: int,
                 latent_prior_weight: float = 1e-4, latent_lr: float = 1e-2,
                 offset_prior_weight: float = 1.0, per_member_adam: bool = False,
                 code_noise: float = 0.0, ea_field: dict | None = None,
                 member_info: list[dict] | None = None):
        super().__init__()
        for key, value in (("scene.family.members", members), ("mode.latent.dim", latent_dim)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"{key}={value}: must be a whole number >= 1.")
        check_learning_rates(latent_lr, "model.latent_lr")
        density = stage.hparams.density
        if density.get("source") != "ea":
            raise ConfigError(f"init.source={density.get('source')}: stage 2 in generative mode "
                              "starts from a generative EA run (init=ea, init.ea_ckpt=<its "
                              "checkpoints/last.ckpt>); forward mode and init=none are for "
                              "single scenes.")
        self.latent_prior_weight = latent_prior_weight
        self.offset_prior_weight = offset_prior_weight
        if not isinstance(per_member_adam, bool):
            raise ConfigError(f"mode.latent.per_member_adam={per_member_adam}: must be true or "
                              "false.")
        self.per_member_adam = per_member_adam
        if isinstance(code_noise, bool) or not isinstance(code_noise, int | float) \
                or not 0 <= code_noise < float("inf"):
            raise ConfigError(f"mode.latent.code_noise={code_noise}: must be a number >= 0 (the "
                              "codes' noise in training, in units of their spread; 0: none).")
        if code_noise and members < 2:
            raise ConfigError(f"mode.latent.code_noise={code_noise} scales the noise by the "
                              "codes' spread over the members, which one member does not "
                              "have: train a family of 2 or more, or set code_noise=0.")
        self.code_noise = float(code_noise)
        if stage.medium.member_offsets not in (0, members):
            raise ConfigError(f"the medium holds feature offsets for {stage.medium.member_offsets} "
                              f"members, but the family has scene.family.members={members}.")
        self.latent_lr = latent_lr
        # the stage registers (and checkpoints) these two; a tuple keeps them out of this
        # module's own registry
        self._fields: tuple[Any, Any] = (stage.light, stage.medium)
        if ea_field is None:  # a fresh run: the EA run's field, codes and members
            ea_field, field, codes, info = load_generative_ea(density.get("ea_ckpt"))
            if tuple(codes.shape) != (members, latent_dim):
                raise ConfigError(
                    f"init.ea_ckpt='{density.get('ea_ckpt')}' holds {codes.shape[0]} codes of "
                    f"dimension {codes.shape[1]}, but this run has scene.family.members="
                    f"{members} and mode.latent.dim={latent_dim}; start from an EA run of the "
                    "same family and mode settings.")
            member_info = None if info is None else \
                [{"name": str(m["name"]), "seed": int(m["seed"])} for m in info]
        else:  # loaded from the stage's checkpoint: the values follow
            field = build_density_field(density_field_factory(ea_field), latent_dim)
            codes = torch.zeros(members, latent_dim)
        self.ea_field = factory_config(density_field_factory(ea_field))  # a config, no code
        self.member_info = member_info
        self.ea = field.requires_grad_(False)
        self._encoding: torch.Tensor | None = None
        self._decoded: list[tuple[Any, Any]] = []  # the step's media: (decoded, leaf)
        self._step: tuple[torch.Tensor, torch.Tensor] | None = None  # members, their steps
        # how many steps drew each member (batches of some members: data.members_per_step)
        self.register_buffer("member_steps", torch.zeros(members, dtype=torch.long))
        self._ground_truths: list[dict[str, torch.Tensor] | None] = []
        self.codes = nn.Parameter(codes.clone())

    @property
    def light(self) -> LatentScatteredLightField:
        """The stage's latent light field."""
        return self._fields[0]

    @property
    def medium(self) -> LatentVoxelisedMedium:
        """The stage's latent medium."""
        return self._fields[1]

    # ------------------------------------------------------------- the family
    def member_names(self) -> list[str]:
        """The members' scene names, in the order of ``codes``' rows (``member<k>`` before a
        run whose EA run recorded none has seen its family)."""
        info = self.member_info
        return [m["name"] for m in info] if info else \
            [f"member{k}" for k in range(self.codes.shape[0])]

    def member_seeds(self) -> list[int]:
        info = self.member_info
        return [int(m["seed"]) for m in info] if info else list(range(self.codes.shape[0]))

    def setup(self, datamodule) -> None:
        """Check the datamodule's family against the members, take its names and seeds if
        the EA run recorded none, and compute the EA features anew in its box."""
        names = [m.name for m in datamodule.family.members]
        if self.member_info is None and len(names) == self.codes.shape[0]:
            self.member_info = [{"name": m.name, "seed": m.seed}
                                for m in datamodule.family.members]
        if names != self.member_names():
            raise DatasetError(f"Family '{datamodule.dataset_dir}' has members {names}, but the "
                               f"EA run this stage starts from was trained on "
                               f"{self.member_names()}; train both stages on one family.")
        self.ea.bbox.copy_(datamodule.bbox.to(self.ea.bbox))
        self._ground_truths = datamodule.member_ground_truths
        self._encoding = None  # at the box the datamodule set

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """The codes and the EA field come with the state; a checkpoint written before
        :attr:`member_steps` was kept starts it at zero."""
        checkpoint["state_dict"].setdefault("scenes.member_steps", torch.zeros_like(
            self.member_steps))

    def settings(self) -> dict:
        """The EA run's field config and the members, which rebuild the family."""
        return {"ea_field": self.ea_field, "member_info": self.member_info}

    def ea_encoding(self) -> torch.Tensor:
        """The frozen EA field's hash features (R^3, F) at the centres of the medium's
        ``density_resolution``^3 cells, ``[z, y, x]``; computed once."""
        if self._encoding is None:
            with torch.no_grad():
                self._encoding = at_cell_centres(self.ea.encode, self.medium.density_resolution,
                                                 self.medium.bbox).flatten(0, 2)
        return self._encoding

    def density_for(self, code: torch.Tensor) -> torch.Tensor:
        """The EA density under ``code`` (d_z,) on the medium's cells (R, R, R, 1), >= 0,
        differentiable in the code."""
        r = self.medium.density_resolution
        dens = self.ea.density_of_encoding(self.ea_encoding(), code)
        return dens.reshape(r, r, r, 1).clamp_min(0.0)

    @property
    def holds_member_offsets(self) -> bool:
        """Whether the medium holds a feature offset per member (what a fold can fold)."""
        return bool(self.medium.member_offsets)

    def offset_of(self, member: int) -> int | None:
        """``member`` where the medium holds the members' feature offsets, else None."""
        return member if self.holds_member_offsets else None

    def member_medium(self, member: int, code: torch.Tensor | None = None):
        """Member ``member``'s medium: voxels, differentiable in the decoder, the code and the
        member's feature offset (where the medium holds them); decoded at ``code`` (d_z,)
        in place of the member's own where given (a training step's noisy code)."""
        with record_function("nrt/medium"):  # a profiler scope (benchmarks.profile_step)
            code = self.codes[member] if code is None else code
            return self.medium.voxels_for(self.density_for(code), code, self.offset_of(member))

    def noisy_codes(self, members: list[int]) -> torch.Tensor | None:
        """The codes a training step decodes ``members``' media at: ``z_k + h s * eps``
        (module docstring, ``code_noise`` h), differentiable in the codes; None without
        noise (the codes themselves)."""
        if not self.code_noise:
            return None
        spread = self.codes.detach().std(0)
        eps = torch.randn(len(members), self.codes.shape[1], device=spread.device,
                          dtype=spread.dtype)
        return self.codes[members] + self.code_noise * spread * eps

    def member_scene(self, member: int) -> tuple[Any, Any]:
        """Member ``member``'s medium (:meth:`member_medium`) and light (the code without
        gradient: the light field does not move the codes)."""
        return (self.member_medium(member),
                self.light.member(member, self.codes[member].detach()))

    # ------------------------------------------------------------- the pairs
    def pairs(self, batch: dict) -> list[tuple[Any, Any]]:
        """The (medium, light) of each member of a training step: every member in the order
        of ``codes``' rows, or the batch's ``step_members`` (M,) when batches draw some
        members (``data.members_per_step``; counted in :attr:`member_steps`). Each medium
        is decoded once and handed out as leaves
        (:meth:`~nrt.modules.fields.voxel_medium.Voxels.as_leaf`): every objective of the
        step reads the same values (the priors too, :meth:`fresh_voxels`), and
        :meth:`backward_media` carries what they left on them into the decoders and codes
        in one backward, instead of one decode and one backward per objective."""
        step = batch.get("step_members")
        self._step = None if step is None else (step, self.member_steps[step].clone())
        if step is not None:
            self.member_steps[step] += 1
        self._decoded = []
        pairs = []
        members = list(range(self.codes.shape[0])) if step is None else step.tolist()
        noisy = self.noisy_codes(members)
        for i, k in enumerate(members):
            decoded = self.member_medium(k, None if noisy is None else noisy[i])
            leaf = decoded.as_leaf()
            self._decoded.append((decoded, leaf))
            with record_function("nrt/light_field"):
                pairs.append((leaf, self.light.member(k, self.codes[k].detach())))
        return pairs

    def scene_of(self, batch: dict) -> torch.Tensor:
        """Each ray's position in :meth:`pairs`: its ``member``, or the member's place in
        the batch's ``step_members``."""
        step = batch.get("step_members")
        if step is None:
            return batch["member"]
        place = torch.full((self.codes.shape[0],), -1, dtype=torch.long, device=step.device)
        place[step] = torch.arange(len(step), device=step.device)
        return place[batch["member"]]

    def uncollided_due(self, cache, step: int) -> list[tuple[int, bool]]:
        """With every member a step, all of them on the cache's schedule; with some members
        a step, each member's light every ``uncollided_every`` of its own steps, the first
        of them included (its first refresh)."""
        if self._step is None:
            if not cache.due(step):
                return []
            return [(i, not cache.fresh) for i in range(self.codes.shape[0])]
        return [(i, n == 0) for i, n in enumerate(self._step[1].tolist())
                if n % cache.every == 0]

    def view_pair(self, batch: dict) -> tuple[Any, Any]:
        """The view's member's medium and light (``member``)."""
        return self.member_scene(int(batch["member"]))

    def fresh_voxels(self) -> list:
        """Every member's medium as the step's objectives read it (the leaves of
        :meth:`pairs`); decoded anew outside a step."""
        if self._decoded:
            return [leaf for _, leaf in self._decoded]
        return [self.member_medium(k) for k in range(self.codes.shape[0])]

    def backward_media(self, backward) -> None:
        """Carry the gradients the step's objectives left on its media (:meth:`pairs`)
        through their decoders into the decoder and the codes, by ``backward`` (the stage's
        ``manual_backward``) of one scalar; nothing when no objective read them."""
        with record_function("nrt/medium"):
            terms = [t for decoded, leaf in self._decoded
                     if (t := decoded.carried_back(leaf)) is not None]
            self._decoded = []
            if terms:
                backward(torch.stack(terms).sum())

    # --------------------------------------------------------------- training
    def priors(self) -> dict[str, torch.Tensor]:
        """``latent_prior``: ``latent_prior_weight * mean_k |z_k|^2``, the codes' Gaussian
        prior, beside their data term (the photos), over the step's members: a code the
        photos do not see this step gets no prior step either (alone, Adam would scale the
        prior's tiny gradient up to steps of ``latent_lr`` toward the origin). With the
        members' feature offsets, ``offset_prior``: ``offset_prior_weight`` times their
        mean over the step's members of the mean over cells of ``|offset_k(x)|^2``."""
        members = None if self._step is None else self._step[0]
        codes = self.codes if members is None else self.codes[members]
        priors = {"latent_prior": self.latent_prior_weight * codes.square().sum(-1).mean()}
        if self.medium.member_offsets:
            priors["offset_prior"] = self.offset_prior_weight * self.medium.offset_square(members)
        return priors

    def step_metrics(self) -> dict[str, torch.Tensor]:
        """``latent_norm``: the codes' mean norm."""
        return {"latent_norm": self.codes.detach().norm(dim=-1).mean()}

    def param_groups(self) -> list[dict]:
        """The codes at ``latent_lr``, without weight decay (the prior is their regulariser),
        ramped in with the medium's rate (``model.medium_rampup``): each member's density
        follows its code, so the codes are the media's parameters too."""
        return [{"params": [self.codes], "lr": self.latent_lr, "weight_decay": 0.0,
                 "ramps_in": True}]

    def member_parameters(self) -> list[tuple[nn.Parameter, int, int]]:
        """With ``per_member_adam``: the codes (a row a member) and the medium's and the
        light's feature offsets (a block of features a member, last axis), which Adam then
        steps per member (:class:`~nrt.stages.member_adam.MemberAdam`); else []."""
        if not self.per_member_adam:
            return []
        k = self.codes.shape[0]
        blocks = [(self.codes, k, 0)]
        return blocks + [(p, k, -1) for p in (*self.medium.member_blocks(),
                                              *self.light.member_blocks())]

    def fold_offsets(self, steps: int, lr: float, kernel: CodeKernel | None = None
                     ) -> dict[str, float]:
        """Fold the members' feature offsets into the medium's shared decoder (the medium's
        ``fold_offsets``, each member's cells weighed by its EA density under its code), so
        that the decoder a new code reads carries what the members recovered; afterwards
        every member decodes from its code alone. With a ``kernel`` (codes drawn around the
        members) the decoder is fitted around each code too. Returns the fit's objective
        before and after (``fold_start``, ``fold_end``), its steps and its seconds."""
        if not self.holds_member_offsets:
            raise ConfigError("fold.steps > 0, but this run's medium holds no member offsets "
                              "(it was trained with mode.latent.member_offsets=false): there is "
                              "nothing to fold. Sample it with fold.steps=0.")
        start = time.perf_counter()
        with torch.no_grad():
            codes = self.codes.detach()
            density = torch.stack([self.density_for(code) for code in codes])
        if not bool((density > 0).any()):
            raise ConfigError("fold.steps > 0, but no member of this run has density on any "
                              "cell (its EA density is zero under every code): there is "
                              "nothing to fold. Sample it with fold.steps=0.")
        before, after = self.medium.fold_offsets(density, codes, steps, lr, kernel)
        return {"fold_start": before, "fold_end": after, "fold_steps": float(steps),
                "fold_s": time.perf_counter() - start}

    # ------------------------------------------------------- grids and export
    @torch.no_grad()
    def property_grids_for(self, code: torch.Tensor, resolution: int,
                           member: int | None = None) -> dict[str, torch.Tensor]:
        """The medium decoded from any code (d_z,) on ``resolution``^3 cells, in the layout
        of :meth:`~nrt.stages.stage.Stage.property_grids`, on the CPU: the EA density under
        the code on the medium's cells, modulated under the code (with member ``member``'s
        feature offset when given), as in training."""
        code = code.to(self.codes)
        voxels = self.medium.voxels_for(self.density_for(code), code, member).detached()
        grids = property_grids(voxels, resolution)
        return {k: v.cpu() for k, v in grids.items()}

    def member_property_grids(self, member: int, resolution: int) -> dict[str, torch.Tensor]:
        """Member ``member``'s medium, decoded from its own code (and its own feature
        offset, where the medium holds them)."""
        return self.property_grids_for(self.codes[member].detach(), resolution,
                                       self.offset_of(member))

    def property_grids(self, resolution: int) -> None:
        """None: a family has one medium per member (:meth:`member_property_grids`)."""
        return None

    def medium_bbox(self) -> torch.Tensor:
        """The box (2, 3) of every member's medium."""
        return self.medium.bbox

    def export(self, run_dir: Path, resolution: int | None) -> dict[str, str]:
        """Write ``members/<name>/medium_grids.npz`` for every member (at ``resolution``,
        default its ground truth's, else 64) and ``latents.npz`` (``codes``, ``names``,
        ``seeds``) into ``run_dir``."""
        run_dir = Path(run_dir)
        res = grid_resolution(resolution, 64, self._ground_truths)
        exports = {}
        for k, name in enumerate(self.member_names()):
            path = run_dir / MEMBERS_DIR / name / MEDIUM_GRIDS_FILE
            path.parent.mkdir(parents=True, exist_ok=True)
            exports[f"medium_grids_{name}"] = str(save_property_grids(
                path, self.member_property_grids(k, res), self.medium.bbox))
        exports["latents"] = save_latents(run_dir, self.codes, self.member_names(),
                                          self.member_seeds())
        return exports
