"""The shapes of config values that nrt's components take, from their constructors' type
hints: a single value where a constructor takes a mapping (``model.lr=0.01`` for stage 2's
per-part rates), a mapping or list where it takes a single value, or null where it takes
none, is refused with a :class:`~nrt.errors.ConfigError` naming the key and the fix, before
anything is built. The schema of a component's arguments is its constructor's signature;
the dict-shaped settings have typed schemas of their own (:mod:`nrt.cli.schema`)."""

from __future__ import annotations

import re
import types
import typing
from collections.abc import Callable, Mapping, Sequence

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from nrt.cli.common import CONFIG_DIR
from nrt.cli.config_errors import value_text
from nrt.errors import ConfigError

SHAPES = ("a mapping", "a list", "a single value", "null")
"""What a config value can be, as :func:`check_arguments` names it."""


def _shape(value) -> str:
    if isinstance(value, Mapping):
        return SHAPES[0]
    if isinstance(value, list | tuple):
        return SHAPES[1]
    return SHAPES[3] if value is None else SHAPES[2]


def _admits(hint) -> set[str]:
    """The shapes of config value that a constructor's type hint accepts; every shape for
    a hint a config cannot be judged against (a module, a tensor)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return set().union(*(_admits(arg) for arg in typing.get_args(hint)))
    if hint is type(None):
        return {SHAPES[3]}
    base = typing.get_origin(hint) or hint
    if base is Callable:
        return {SHAPES[0]}  # code comes from a config with a _target_, a mapping
    if isinstance(base, type):
        if issubclass(base, Mapping):
            return {SHAPES[0]}
        if issubclass(base, str | int | float | bool):
            return {SHAPES[2]}
        if issubclass(base, Sequence):
            return {SHAPES[1]}
    return set(SHAPES)


def _hints(target: str) -> dict:
    """Type hints of the constructor arguments of ``target`` (those of base classes
    included, for ``**kwargs`` passed on); empty when it cannot be imported (the
    instantiation reports that)."""
    from hydra.utils import get_class

    try:
        cls = get_class(target)
    except Exception:  # noqa: BLE001 - a bad _target_ is reported where it is built
        return {}
    hints: dict = {}
    for klass in reversed(cls.__mro__):
        if "__init__" in vars(klass):
            try:
                hints.update(typing.get_type_hints(klass.__init__))
            except Exception:  # noqa: BLE001 - unresolvable hints are not judged
                continue
    return hints


def _default(key: str, choices: Mapping[str, str], depth: int = 0):
    """The value the config files give ``key`` (``model.lr``) for the chosen options, with
    an interpolation of another key (``${losses.weights}``) followed; None when it cannot
    be told."""
    parts = key.split(".")
    for i in range(len(parts), 0, -1):
        group = "/".join(parts[:i])
        path = CONFIG_DIR / group / f"{choices.get(group)}.yaml"
        if group not in choices or not path.is_file():
            continue
        value = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
        for part in parts[i:]:
            value = value.get(part) if isinstance(value, Mapping) else None
        link = re.fullmatch(r"\$\{([\w.]+)\}", value) if isinstance(value, str) else None
        if link and depth < 4:
            return _default(link.group(1), choices, depth + 1)
        return value
    return None


def _shape_error(key: str, value, admits: set[str], default, group: bool) -> ConfigError:
    wanted = " or ".join(s for s in SHAPES if s in admits)
    text = f"{key}={value_text(value)}: must be {wanted}, not {_shape(value)}."
    if group:
        text += (f" It is the config group {key.replace('.', '/')}: choose an option with "
                 f"{key.replace('.', '/')}=<name> (conf/{key.replace('.', '/')}/).")
    elif isinstance(default, Mapping) and default:
        entries = list(map(str, default))
        if _shape(value) == SHAPES[2] and all(_shape(v) == SHAPES[2] for v in default.values()):
            how = "set each entry: " + " ".join(f"{key}.{e}={value}" for e in entries)
        else:
            how = f"set them one at a time ({key}.{entries[0]}=<value>)"
        text += f" Its entries are {', '.join(entries)}: {how}."
    elif default is not None:
        text += f" The default is {key}={value_text(default)}."
    elif SHAPES[1] in admits and _shape(value) == SHAPES[2]:
        text += f" For one entry, give a list of one: {key}=[{value}]."
    return ConfigError(text + " `--cfg job` prints the composed config.")


def check_arguments(cfg: DictConfig, choices: Mapping[str, str] | None = None) -> None:
    """Refuse a value of the wrong shape for a constructor argument of an nrt component
    (``model``, ``data``, ``callbacks``): a single value where the constructor takes a
    mapping (``model.lr=0.01`` for stage 2's per-part rates), a mapping or list where it
    takes a single value, null where it takes none. The shape comes from the constructor's
    type hints; ``choices`` (Hydra's chosen config options) let the message list the
    entries the default gives. Runs before anything is built."""
    choices = dict(choices or {})
    roots = {"model": cfg.get("model"), "data": cfg.get("data"),
             **{f"callbacks.{k}": v for k, v in (cfg.get("callbacks") or {}).items()
                if str(v.get("_target_", "")).startswith("nrt.")}}
    for root, node in roots.items():
        if node is not None:
            _check_node(_resolved(node), root, choices)


def _resolved(node: DictConfig) -> dict:
    """``node`` as a plain dict with its interpolations resolved, except those of Hydra's
    own ``${hydra:...}`` resolver outside a Hydra run (a composed config in a test or a
    benchmark): they are left as the strings they are (a path, never a shape mistake)."""
    raw = OmegaConf.to_container(node, resolve=False)
    out = {}
    for key, value in raw.items():
        if isinstance(value, str) and "${hydra:" in value and not HydraConfig.initialized():
            out[key] = value
            continue
        value = node[key]
        out[key] = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) \
            else value
    return out


def _check_node(node, key: str, choices: Mapping[str, str]) -> None:
    if not isinstance(node, Mapping):
        return
    target = node.get("_target_")
    hints = _hints(target) if isinstance(target, str) and target.startswith("nrt.") else {}
    for name, value in node.items():
        if name.startswith("_"):
            continue
        admits = _admits(hints[name]) if name in hints else set(SHAPES)
        if _shape(value) not in admits:
            group = f"{key}.{name}".replace(".", "/")
            raise _shape_error(f"{key}.{name}", value, admits,
                               _default(f"{key}.{name}", choices),
                               group in choices and (CONFIG_DIR / group).is_dir())
        _check_node(value, f"{key}.{name}", choices)
