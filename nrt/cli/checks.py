"""The checks of a composed ``nrt-train`` config beyond what a type says, made before any
component is built or data is loaded, each refusing with a :class:`~nrt.errors.ConfigError`
naming the key: the compute ``budget``'s counts and shares and the root config's scalar
options (whole numbers in a range, rules between keys: one message states both, so they
are not typed at composition), objectives that cannot be imported or do not fit the stage,
and modes that do not fit the scene or stage.

Types are checked elsewhere: the dict-shaped settings by their schemas as the config is
composed (:mod:`nrt.cli.schema`), the shapes of components' arguments by their
constructors' hints (:func:`~nrt.cli.shapes.check_arguments`, which nrt-train runs with
these). What a component alone can judge (names, schedules, learning rates) its
constructor checks, with the same error."""

from __future__ import annotations

from collections.abc import Callable, Mapping

from omegaconf import DictConfig, OmegaConf

from nrt.cli.config_errors import value_text
from nrt.cli.shapes import check_arguments
from nrt.errors import ConfigError

__all__ = ["check_arguments", "check_budget", "check_mode", "check_mode_fits", "check_objectives",
           "check_options", "check_processes", "processes"]

ZERO_ALLOWED = ("light_degree", "sky_env_directions", "sky_phase_directions", "photo_twins")
"""Counts of ``budget`` for which 0 is meaningful (SH band 0 only; one of the two MIS
strategies left out; no photo ray with a twin); every other count must be at least 1."""

OPTIONAL_COUNTS = ("val_views", "spp_final")
"""Counts of ``budget`` that may be null (all held-out views; the training spp throughout)."""

FRACTIONS = ("light_warmup",)
"""Shares of a run in ``budget``, in [0, 1)."""

WEIGHTS = ("extinction_prior",)
"""Loss weights a preset tunes in ``budget`` (numbers >= 0)."""

RUN_COUNTS = ("stage.steps", "stage.rays_per_batch", "data.steps_per_epoch")
"""Counts outside ``budget`` that a user may override directly."""


def _leaves(node, key: str):
    """``(dotted key, value)`` of every leaf of a plain container; a list of numbers is
    one leaf."""
    if isinstance(node, dict):
        for name, child in node.items():
            yield from _leaves(child, f"{key}.{name}")
    else:
        yield key, node


def _is_count(value, least: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= least


def _count_error(key: str, value, least: int) -> ConfigError:
    return ConfigError(f"{key}={value}: must be a whole number >= {least} (a count of steps, "
                    "rays, samples, cells or layers; for a list, each entry). Fix the "
                    "override, or leave the key to the preset (conf/preset/).")


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def check_budget(cfg: DictConfig) -> None:
    """Refuse counts and shares that no run can use (``budget.ea.steps=-3``, a zero batch
    size, a negative resolution, ``budget_s=-5``) with the key in the message, before
    anything is built or loaded. Schedules (``*upsample_at``) are checked by their stage."""
    budget = OmegaConf.to_container(cfg.budget, resolve=True)
    for key, value in _leaves(budget, "budget"):
        name = key.rsplit(".", 1)[-1]
        if isinstance(value, bool) or name.endswith("upsample_at") or \
                (name in OPTIONAL_COUNTS and value is None):
            continue
        if name in FRACTIONS:
            if not _is_number(value) or not 0 <= value < 1:
                raise ConfigError(f"{key}={value}: must be a share of the run in [0, 1).")
            continue
        if name in WEIGHTS:
            if not _is_number(value) or value < 0:
                raise ConfigError(f"{key}={value}: must be a loss weight >= 0 (0 leaves the "
                                  "term out).")
            continue
        least = 0 if name in ZERO_ALLOWED else 1
        items = value if isinstance(value, list) else [value]
        if not items or not all(_is_count(item, least) for item in items):
            raise _count_error(key, value, least)
    rte = budget.get("rte", {})
    twins, rays = rte.get("photo_twins", 0), rte.get("photo_rays")
    if rays is not None and twins > rays:
        raise ConfigError(f"budget.rte.photo_twins={twins}: must be at most "
                          f"budget.rte.photo_rays ({rays}), the photo rays a twin can pair "
                          "with. Lower it, or set it to ${budget.rte.photo_rays} "
                          "(ablation=photo_twins) to pair them all.")
    for name in ("photo_rays", "vre_rays"):  # the first rays of each batch; more are not there
        wanted, batch = rte.get(name), rte.get("rays_per_batch")
        if wanted is not None and batch is not None and wanted > batch:
            raise ConfigError(f"budget.rte.{name}={wanted}: must be at most "
                              f"budget.rte.rays_per_batch ({batch}), the rays a step draws "
                              f"(the objective takes the first {name} of them). Raise "
                              f"budget.rte.rays_per_batch with it, as "
                              "conf/ablation/photo_rays_1024.yaml does.")
    for key in RUN_COUNTS:
        if not _is_count(OmegaConf.select(cfg, key), 1):
            raise _count_error(key, OmegaConf.select(cfg, key), 1)
    _check_option(cfg, "budget_s")


SEEDS = 2**32
"""Seeds are whole numbers below this (what NumPy and Lightning accept)."""

_ABSENT = object()


def _is_seed(value) -> bool:
    return _is_count(value, 0) and value < SEEDS


OPTIONS: dict[str, tuple[str, Callable[[object], bool]]] = {
    "seed": ("a whole number in [0, 2^32), the seed of every random draw of the run",
             _is_seed),
    "resume": ("false, true (continue the newest run of this scene and stage) or the path "
               "of a .ckpt file", lambda v: v is None or isinstance(v, bool | str)),
    "budget_s": ("a positive number of seconds of training (or null for no time limit)",
                 lambda v: v is None or (_is_number(v) and v > 0)),
    "threads": ("a whole number >= 1 of torch threads per process, or null (the cores "
                "shared among the jobs a joblib launcher runs at once and a run's processes)",
                lambda v: v is None or _is_count(v, 1)),
    "compile": ("true or false (torch.compile of each stage's hot code, nrt/compile.py)",
                lambda v: isinstance(v, bool)),
    "fused_lookups": ("true or false (the grid and environment-map lookups by fused C++ "
                      "kernels on the CPU, nrt/physics/fused_lookup.py, fused_envmap.py)",
                      lambda v: isinstance(v, bool)),
}
"""The scalar options of the root configs, what each must be, and the test of it."""


def check_options(cfg: DictConfig) -> None:
    """Refuse a scalar option of the root config (:data:`OPTIONS`: ``seed=abc``,
    ``compile=maybe``) that no run can use, naming the key, before anything is
    built or loaded; options a command does not have are skipped."""
    for key in OPTIONS:
        _check_option(cfg, key)


def _check_option(cfg: DictConfig, key: str) -> None:
    what, valid = OPTIONS[key]
    value = OmegaConf.select(cfg, key, default=_ABSENT)
    if value is not _ABSENT and not valid(value):
        raise ConfigError(f"{key}={value_text(value)}: must be {what}. Fix the override, or "
                          "leave the key to its default (`--cfg job` prints the config).")


def voxel_stage(cls) -> bool:
    """Whether ``cls`` (a model's ``_target_``) is a stage that learns voxel media
    (:attr:`nrt.stages.stage.Stage.voxel_media`)."""
    from nrt.stages.stage import Stage

    return isinstance(cls, type) and issubclass(cls, Stage) and cls.voxel_media


def check_objectives(cfg: DictConfig) -> dict[str, type]:
    """The unit (a subclass of :class:`~nrt.losses.objective.Objective`) each entry of
    ``losses.objectives`` names, by name (none for a stage without objectives); an entry
    without ``_target_``, whose ``_target_`` cannot be imported or is no objective, or
    without ``_partial_: true`` is refused naming its key, before anything is built.
    A prior on voxels given to a stage without them (the paper's formulation) is refused
    too. Which objectives have weights the stage checks as it builds them."""
    from hydra.utils import get_object

    from nrt.losses.objective import objective_class

    entries = OmegaConf.select(cfg, "losses.objectives")
    if entries is None:
        return {}
    classes = {}
    for name, entry in OmegaConf.to_container(entries, resolve=True).items():
        key = f"losses.objectives.{name}"
        target = entry.get("_target_") if isinstance(entry, Mapping) else None
        if not isinstance(target, str):
            raise ConfigError(f"{key}={value_text(entry)}: an objective is a config with "
                              "`_target_: <module>.<Class>` (a subclass of nrt.losses.objective."
                              "Objective) and `_partial_: true` (conf/losses/<stage>.yaml).")
        try:
            unit = get_object(target)
        except Exception as exc:  # noqa: BLE001 - Hydra's import errors vary by cause
            raise ConfigError(f"{key}._target_={target}: cannot import it ({exc}). It names "
                              "an objective's class by its module path "
                              "(nrt.losses.<module>.<Class>).") from None
        classes[name] = objective_class(unit, key)
        if entry.get("_partial_") is not True:
            raise ConfigError(f"{key} lacks `_partial_: true`: the stage builds the objective "
                              "itself, with its name and weight schedule.")
    model = OmegaConf.select(cfg, "model._target_")
    priors = [name for name, unit in classes.items() if unit.reads_voxels]
    if priors and model and not voxel_stage(get_object(model)):
        raise ConfigError(f"losses.objectives.{priors[0]} is a prior on a voxel medium, which "
                          f"this stage ({model}) does not have: the paper's formulation "
                          "(experiment=rte_paper) learns a SIREN medium. Drop it "
                          f"(~losses.objectives.{priors[0]} ~losses.weights.{priors[0]}, or "
                          "the ablation that adds it), or train the split stage 2 (stage=rte).")
    return classes


GENERATIVE_STAGES = ("ea", "rte")
"""The stages built in ``mode=generative`` (``conf/mode_stage/generative_<stage>.yaml``)."""

LATENT_COUNTS = {"dim": "d_z, the size of a latent code",
                 "modulation_hidden": "the width of the modulation MLP M(z)"}
"""Counts of ``mode.latent`` (each at least 1) and what they count."""


def check_mode_fits(cfg: DictConfig) -> bool:
    """Refuse a mode that does not fit the scene or stage, reading only ``mode.name``,
    ``scene.family`` and ``stage.name`` (so that it can run before the config is resolved:
    a generative stage on one scene leaves the family's keys unresolvable):
    ``mode=generative`` trains stages 1 and 2 on a scene family, and a family trains only in
    that mode. Whether the mode is generative."""
    mode = OmegaConf.select(cfg, "mode.name", default="single")
    family = OmegaConf.select(cfg, "scene.family") is not None
    if mode not in ("single", "generative"):
        raise ConfigError(f"mode.name={mode}: must be single or generative (mode=single|"
                          "generative picks conf/mode/<name>.yaml).")
    if mode == "single" and family:
        raise ConfigError(f"scene={cfg.scene.name} is a family of scenes (scene.family), "
                          "which nrt-train trains only as a whole with mode=generative "
                          f"(nrt-train stage=ea mode=generative scene={cfg.scene.name}); to "
                          "train one member alone, pass scene.path=<member folder> "
                          "scene.name=<member name> with a single scene config.")
    if mode == "single":
        return False
    if not family:
        raise ConfigError(f"mode=generative learns a distribution over a family of scenes, "
                          f"but scene={cfg.scene.name} is one scene (it has no scene.family). "
                          "Add scene=family (docs/scenes.md, \"Scene families\"), or drop "
                          "mode=generative to train this scene alone.")
    if cfg.stage.name not in GENERATIVE_STAGES:
        raise ConfigError(f"mode=generative is built for stage=ea and stage=rte; stage="
                          f"{cfg.stage.name} in generative mode is not built. Run nrt-train "
                          "stage=ea mode=generative scene=family, then stage=rte.")
    return True


def check_mode(cfg: DictConfig) -> None:
    """Refuse a mode that does not fit the scene or stage (:func:`check_mode_fits`), and
    latent settings no run can use, before anything is built or loaded: ``mode.latent``
    holds counts >= 1, a non-negative ``init_std``, ``prior_weight``,
    ``offset_prior_weight`` and ``code_noise``, a positive ``lr`` and booleans ``input``,
    ``member_offsets``, ``light_offsets`` and ``per_member_adam``."""
    if not check_mode_fits(cfg):
        return
    single = [name for name, unit in check_objectives(cfg).items() if not unit.families]
    if single:
        raise ConfigError(f"stage={cfg.stage.name} mode=generative takes each objective over "
                          f"a family's scenes, but losses.objectives.{single[0]} "
                          f"({cfg.losses.objectives[single[0]]._target_}) takes one scene: the "
                          "paper's formulation (experiment=rte_paper) is a single-scene "
                          "formulation. Drop the experiment.")
    environments = OmegaConf.select(cfg, "stage.environments")
    if any(isinstance(e, int) and e != 0 for e in environments or []):
        raise ConfigError(f"stage.environments={list(environments)}: a family trains on its "
                          "shared training environment only (position 0; position 1 is the "
                          "held-back sky for novel illumination). Set stage.environments=[0].")
    latent = OmegaConf.to_container(cfg.mode.latent, resolve=True)
    for name, what in LATENT_COUNTS.items():
        if not _is_count(latent.get(name), 1):
            raise ConfigError(f"mode.latent.{name}={latent.get(name)}: must be a whole number "
                              f">= 1 ({what}).")
    for name in ("init_std", "prior_weight", "offset_prior_weight", "code_noise"):
        if not _is_number(latent.get(name, 0)) or latent.get(name, 0) < 0:
            raise ConfigError(f"mode.latent.{name}={latent.get(name)}: must be a number >= 0.")
    if not _is_number(latent.get("lr")) or latent["lr"] <= 0:
        raise ConfigError(f"mode.latent.lr={latent.get('lr')}: a learning rate must be a "
                          "positive number.")
    for name, what in (("input", "whether stage 1's density MLP reads the code beside the "
                                 "features"),
                       ("member_offsets", "whether each member's stage-2 medium reads its own "
                                          "feature offset"),
                       ("light_offsets", "whether each member's stage-2 light reads its own "
                                         "feature offset"),
                       ("per_member_adam", "whether stage 2's Adam steps each member's code "
                                           "and offsets only on the steps that draw it")):
        if not isinstance(latent.get(name, False), bool):
            raise ConfigError(f"mode.latent.{name}={latent.get(name)}: must be true or false "
                              f"({what}).")


SINGLE_PROCESS_STAGES = ("dpt",)
"""Stages that train in one process only: the baseline chooses its views and Mitsuba's
seeds from the run's seed and step alone (every rank would render the same views with the
same noise) and renders on the device Dr.Jit picks, not its rank's."""

LIGHTNING_STRATEGIES = ("ddp", "fsdp", "deepspeed")
"""Lightning's own strategies of several processes (named by strings)."""


def processes(cfg: DictConfig) -> int:
    """How many processes ``cfg.trainer`` trains in (:func:`nrt.distributed.process_count`)."""
    from nrt.distributed import process_count

    trainer = {key: OmegaConf.select(cfg, f"trainer.{key}")
               for key in ("strategy", "devices", "accelerator", "num_nodes")}
    if OmegaConf.is_config(trainer["strategy"]):
        trainer["strategy"] = OmegaConf.to_container(trainer["strategy"], resolve=True)
    if OmegaConf.is_config(trainer["devices"]):
        trainer["devices"] = OmegaConf.to_container(trainer["devices"], resolve=True)
    return process_count(trainer)


def check_processes(cfg: DictConfig, choices: Mapping[str, str] | None = None) -> None:
    """Refuse a run in several processes that nrt cannot train, before anything is built:
    Lightning's own ``ddp`` strategies (torch's DistributedDataParallel, which cannot follow
    stage 2's grids that double or its several backward passes a step) and the stages of
    :data:`SINGLE_PROCESS_STAGES`. ``choices``: the config groups chosen (Hydra's
    ``runtime.choices``), to name the trainer."""
    strategy = OmegaConf.select(cfg, "trainer.strategy")
    if isinstance(strategy, str) and strategy.startswith(LIGHTNING_STRATEGIES):
        raise ConfigError(
            f"trainer.strategy={strategy}: nrt trains in several processes with its own "
            "strategy, which averages each gradient over the ranks before every step "
            "(nrt.distributed.GradientAveraging); Lightning's wraps the stage in torch's "
            "DistributedDataParallel, which cannot follow grids that double or several "
            "backward passes a step. Use trainer=ddp_cpu (2 CPU processes) or trainer=ddp "
            "(one process per GPU).")
    count = processes(cfg)
    stage = OmegaConf.select(cfg, "stage.name")
    if count > 1 and stage in SINGLE_PROCESS_STAGES:
        trainer = (choices or {}).get("trainer") or "<several processes>"
        raise ConfigError(
            f"stage={stage} trains in one process, but trainer={trainer} trains in {count}: "
            "the baseline picks its views and Mitsuba's seeds from the run's seed and step "
            "alone, so every rank would render the same views with the same noise, on the "
            "device Mitsuba picks. Run it with trainer=cpu (or trainer=gpu); to run several "
            "baselines at once, sweep them: nrt-train -m hydra/launcher=nrt_joblib "
            f"stage={stage} seed=0,1.")
