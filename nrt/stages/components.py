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
``load_from_checkpoint`` rebuilds the stage (:mod:`nrt.stages.checkpoints`: the format).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

from hydra.utils import instantiate

from nrt.errors import ConfigError


def factory_config(factory: functools.partial) -> dict:
    """The Hydra config (``_target_``, ``_partial_: true``, keywords) that builds ``factory``;
    keywords that are factories themselves become nested configs."""
    keywords = {k: factory_config(v) if isinstance(v, functools.partial) else v
                for k, v in factory.keywords.items()}
    func = factory.func
    return {"_target_": f"{func.__module__}.{func.__qualname__}", "_partial_": True,
            **keywords}


def as_factory(component, group: str, key: str | None = None, home: str | None = None
               ) -> functools.partial:
    """A stage's ``component`` argument as a factory: a partial as Hydra made it, or a config
    dict with ``_target_`` (a checkpoint's record) instantiated. Errors name the config
    group ``group`` (``light_field``: the key ``model.light_field``, the files
    ``conf/model/light_field/<name>.yaml``), or ``key`` and ``home`` for a component that
    is no group's."""
    key = key or f"model.{group}"
    home = home or f"conf/model/{group}/<name>.yaml"
    if isinstance(component, dict):
        if "_target_" not in component:
            raise ConfigError(f"{key} has no `_target_`: give it the class to build "
                              f"(`_target_: <module>.<Class>`, `_partial_: true`; {home}).")
        component = instantiate(component, _convert_="all")
    if isinstance(component, functools.partial):
        return component
    raise ConfigError(
        f"{key} is a built {type(component).__name__}, but the stage builds it itself: give "
        f"its config ({home}) `_partial_: true` beside its `_target_`.")


def stage_2_components(light_field, medium, objectives: Mapping[str, Any] | None
                       ) -> tuple[tuple[functools.partial, functools.partial, dict], tuple]:
    """A stage-2 formulation's components: the factories of its light field, medium and
    objectives (by name), and the configs it records in its hyperparameters for each (a
    checkpoint pickles no code)."""
    make_objectives, objective_configs = objective_components(objectives)
    make_light = as_factory(light_field, "light_field")
    make_medium = as_factory(medium, "medium")
    return ((make_light, make_medium, make_objectives),
            (factory_config(make_light), factory_config(make_medium), objective_configs))


def objective_components(objectives: Mapping[str, Any] | None
                         ) -> tuple[dict[str, functools.partial], dict[str, dict]]:
    """A stage's ``objectives`` argument (``losses.objectives``: name -> a unit's factory,
    or its config as a checkpoint records it) as factories by name, and their configs (what
    the stage records); None is refused."""
    if objectives is None:
        raise ConfigError("losses.objectives is missing: a stage-2 model takes its objectives "
                          "from losses.objectives (conf/losses/<stage>.yaml).")
    factories = {name: as_factory(config, "objectives", key=f"losses.objectives.{name}",
                                  home="conf/losses/<stage>.yaml")
                 for name, config in objectives.items()}
    return factories, {name: factory_config(f) for name, f in factories.items()}
