"""Checks of a composed ``nrt-train`` config that need nothing but the config: counts and
shares of the compute ``budget`` that no run can use are refused with an
:class:`~nrt.errors.ConfigError` naming the key, before any component is built or data is
loaded. What a component alone can judge (names, schedules, learning rates) its
constructor checks, with the same error."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from nrt.errors import ConfigError

ZERO_ALLOWED = ("light_degree", "sky_env_directions", "sky_phase_directions")
"""Counts of ``budget`` for which 0 is meaningful (SH band 0 only; one of the two MIS
strategies left out); every other count must be at least 1."""

FRACTIONS = ("light_warmup",)
"""Shares of a run in ``budget``, in [0, 1)."""

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
                (name == "val_views" and value is None):
            continue
        if name in FRACTIONS:
            if not _is_number(value) or not 0 <= value < 1:
                raise ConfigError(f"{key}={value}: must be a share of the run in [0, 1).")
            continue
        least = 0 if name in ZERO_ALLOWED else 1
        items = value if isinstance(value, list) else [value]
        if not items or not all(_is_count(item, least) for item in items):
            raise _count_error(key, value, least)
    for key in RUN_COUNTS:
        if not _is_count(OmegaConf.select(cfg, key), 1):
            raise _count_error(key, OmegaConf.select(cfg, key), 1)
    if cfg.budget_s is not None and (not _is_number(cfg.budget_s) or cfg.budget_s <= 0):
        raise ConfigError(f"budget_s={cfg.budget_s}: must be a positive number of seconds of "
                       "training (or null for no time limit).")


GENERATIVE_STAGES = ("ea", "rte")
"""The stages built in ``mode=generative`` (``conf/mode_stage/generative_<stage>.yaml``)."""

SPLIT_OBJECTIVES = ("photo", "transport")
"""The objectives of generative stage 2 (:mod:`nrt.modules.stages.rte_split`)."""

LATENT_COUNTS = {"dim": "d_z, the size of a latent code",
                 "modulation_hidden": "the width of the modulation MLP M(z)"}
"""Counts of ``mode.latent`` (each at least 1) and what they count."""


def check_mode(cfg: DictConfig) -> None:
    """Refuse a mode that does not fit the scene or stage, and latent settings no run can
    use, before anything is built or loaded: ``mode=generative`` trains stages 1 and 2 on a scene
    family (``scene.family``), a family trains only in that mode, and ``mode.latent`` holds
    counts >= 1, a non-negative ``init_std`` and ``prior_weight`` and a positive ``lr``."""
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
        return
    if not family:
        raise ConfigError(f"mode=generative learns a distribution over a family of scenes, "
                          f"but scene={cfg.scene.name} is one scene (it has no scene.family). "
                          "Add scene=family (README \"Scene families\"), or drop "
                          "mode=generative to train this scene alone.")
    if cfg.stage.name not in GENERATIVE_STAGES:
        raise ConfigError(f"mode=generative is built for stage=ea and stage=rte; stage="
                          f"{cfg.stage.name} in generative mode is not built. Run nrt-train "
                          "stage=ea mode=generative scene=family, then stage=rte.")
    weights = set(OmegaConf.select(cfg, "losses.weights", default={}) or {})
    if cfg.stage.name == "rte" and not weights <= set(SPLIT_OBJECTIVES):
        raise ConfigError(f"stage=rte mode=generative trains the split formulation (objectives "
                          f"{list(SPLIT_OBJECTIVES)}), but losses.weights names "
                          f"{sorted(weights)}: the paper's formulation (experiment=rte_paper) "
                          "is a single-scene formulation. Drop the experiment.")
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
    for name in ("init_std", "prior_weight"):
        if not _is_number(latent.get(name)) or latent[name] < 0:
            raise ConfigError(f"mode.latent.{name}={latent.get(name)}: must be a number >= 0.")
    if not _is_number(latent.get("lr")) or latent["lr"] <= 0:
        raise ConfigError(f"mode.latent.lr={latent.get('lr')}: a learning rate must be a "
                          "positive number.")
