"""Components a stage receives from Hydra: factories, their protocols, and how checkpoints
record them.

A model config picks its components by config group (stage 1's
``model/density_field=<name>``; stage 2's ``model/light_field=<name>``,
``model/medium=<name>``), and stage 2 its objectives by the entries of
``losses.objectives`` (:func:`objective_components`). Each option (a file, or an entry)
has a ``_target_`` and ``_partial_: true``: Hydra hands the stage a
:func:`functools.partial`, and the stage calls it with what only it knows (the scene's
effects, the EA density field; an objective's name and weight schedule).
The stage then checks the component against the protocol it needs
(:mod:`nrt.modules.fields.protocols`), so a representation that does not fit is refused naming
the config group and the members it lacks.

Checkpoints must hold no pickled code (``torch.load`` reads them with ``weights_only``), so
a stage records each factory as its config (:func:`factory_config`, a plain dict with
``_target_``), and :func:`as_factory` turns that config back into the factory when
``load_from_checkpoint`` rebuilds the stage. Checkpoints written before these were
components hold the factory's keywords alone (no ``_target_``); a stage reads them with a
``legacy`` translation. Those written before the objectives were components record none;
the stage builds its formulation's objectives of that time.

Checkpoints and run folders written before the layout of 2026-11-23 (encodings, fields and
stages in subpackages of :mod:`nrt.modules`) name their classes by the old module paths;
:data:`MOVED_MODULES` maps those to today's, and :func:`current_target` applies it where a
recorded ``_target_`` is read (here, and ``nrt-eval`` for a run's model).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import Any

from hydra.utils import instantiate

from nrt.errors import ConfigError

MOVED_MODULES: dict[str, str] = {
    f"nrt.modules.{name}": f"nrt.modules.{home}.{name}"
    for home, names in (("encodings", ("hash_grid", "siren", "activations")),
                        ("fields", ("ea_field", "light_field", "sh_light_field", "medium",
                                    "voxel_medium", "protocols", "coarse_to_fine",
                                    "latent_grid")),
                        ("stages", ("stage", "ea", "generative_ea", "rte", "rte_split", "dpt",
                                    "schedules", "components", "generative_rte")))
    for name in names}
"""Old module path -> today's, for ``_target_`` strings recorded before the layout."""


def current_target(target: str) -> str:
    """A recorded ``_target_`` (``module.Class``) with a pre-layout module path replaced by
    today's (:data:`MOVED_MODULES`); others unchanged."""
    module, _, name = target.rpartition(".")
    return f"{MOVED_MODULES.get(module, module)}.{name}"


def current_targets(config):
    """``config`` (nested dicts and lists) with every ``_target_`` made current."""
    if isinstance(config, dict):
        return {k: current_target(v) if k == "_target_" and isinstance(v, str)
                else current_targets(v) for k, v in config.items()}
    if isinstance(config, list):
        return [current_targets(v) for v in config]
    return config


def factory_config(factory: functools.partial) -> dict:
    """The Hydra config (``_target_``, ``_partial_: true``, keywords) that builds ``factory``;
    keywords that are factories themselves become nested configs."""
    keywords = {k: factory_config(v) if isinstance(v, functools.partial) else v
                for k, v in factory.keywords.items()}
    func = factory.func
    return {"_target_": f"{func.__module__}.{func.__qualname__}", "_partial_": True,
            **keywords}


def as_factory(component, group: str, legacy: Callable[[dict], dict] | None = None,
               key: str | None = None, home: str | None = None) -> functools.partial:
    """A stage's ``component`` argument as a factory: a partial as Hydra made it, a config
    dict with ``_target_`` (a checkpoint's record) instantiated, or a dict of keywords from
    an older checkpoint translated by ``legacy`` into such a config. Errors name the config
    group ``group`` (``light_field``: the key ``model.light_field``, the files
    ``conf/model/light_field/<name>.yaml``), or ``key`` and ``home`` for a component that
    is no group's."""
    key = key or f"model.{group}"
    home = home or f"conf/model/{group}/<name>.yaml"
    if isinstance(component, dict):
        if "_target_" not in component and legacy is None:
            raise ConfigError(f"{key} has no `_target_`: give it the class to build "
                              f"(`_target_: <module>.<Class>`, `_partial_: true`; {home}).")
        config = component if "_target_" in component else legacy(component)
        component = instantiate(current_targets(config), _convert_="all")
    if isinstance(component, functools.partial):
        return component
    raise ConfigError(
        f"{key} is a built {type(component).__name__}, but the stage builds it itself: give "
        f"its config ({home}) `_partial_: true` beside its `_target_`.")


def objective_components(objectives: Mapping[str, Any] | None, legacy: Mapping[str, str]
                         ) -> tuple[dict[str, functools.partial], dict[str, dict]]:
    """A stage's ``objectives`` argument (``losses.objectives``: name -> a unit's factory,
    or its config as a checkpoint records it) as factories by name, and their configs (what
    the stage records). None (a checkpoint written before objectives were configs) gives
    ``legacy`` (name -> the unit's class), the objectives of that time."""
    if objectives is None:
        objectives = {name: {"_target_": target, "_partial_": True}
                      for name, target in legacy.items()}
    factories = {name: as_factory(config, "objectives", key=f"losses.objectives.{name}",
                                  home="conf/losses/<stage>.yaml")
                 for name, config in objectives.items()}
    return factories, {name: factory_config(f) for name, f in factories.items()}


def legacy_config(target: str) -> Callable[[dict], dict]:
    """The ``legacy`` translation of :func:`as_factory` for a component whose keywords did
    not change: ``_target_`` and ``_partial_`` added."""
    return lambda keywords: {"_target_": target, "_partial_": True, **keywords}
