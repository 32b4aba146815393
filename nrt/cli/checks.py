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
