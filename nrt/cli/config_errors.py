"""Config mistakes as nrt's one-paragraph errors.

Hydra and OmegaConf report a mistake on the command line or in the config tree with their
own exceptions: an unknown key or group option, an override they cannot parse, a key
deleted that is not there, an interpolation that names no key, a ``_target_`` that cannot
be imported or called with the keys its config holds. :func:`config_mistake` turns each
into a :class:`~nrt.errors.ConfigError` that names the key and the fix, which the commands
print as ``nrt: error: ...`` with exit status 2 (:func:`nrt.cli.common.run_app`). Any
other exception is left alone: a bug keeps its traceback.
"""

from __future__ import annotations

import difflib
import re
import sys
import types

from hydra.errors import (
    ConfigCompositionException,
    InstantiationException,
    MissingConfigException,
    OverrideParseException,
)
from omegaconf.errors import (
    ConfigAttributeError,
    ConfigKeyError,
    GrammarParseError,
    InterpolationResolutionError,
    MissingMandatoryValue,
)

from nrt.errors import ConfigError, NrtError


def _paragraph(text: str) -> str:
    """Hydra's and OmegaConf's multi-line messages as one line, without their
    ``full_key:``/``object_type=`` trailers, search paths and documentation links."""
    keep = [line.strip() for line in str(text).splitlines()
            if line.strip() and not line.strip().startswith(
                ("full_key:", "object_type=", "See https://", "Config search path",
                 "provider=", "Set the environment"))]
    return " ".join(keep).rstrip(".")


def _given(key: str) -> str | None:
    """The command-line override of ``key`` (``key=value``, ``+key=...``), if any."""
    for arg in sys.argv[1:]:
        name = arg.split("=", 1)[0].lstrip("+~")
        if name == key:
            return arg
    return None


def _close(name: str, choices) -> str:
    match = difflib.get_close_matches(name, [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean '{match[0]}'?)" if match else ""


def _unknown_key(exc: ConfigKeyError | ConfigAttributeError, command: str) -> ConfigError:
    key = exc.full_key or exc.key
    parent = exc.parent_node
    options = [] if parent is None or not hasattr(parent, "keys") else list(parent.keys())
    if "/" in str(key):  # group/option syntax for a group this composition does not have
        return _no_group(str(key), command)
    near = _close(str(exc.key), options)
    where = key.rsplit(".", 1)[0] if "." in str(key) else "the config's top level"
    shown = f" Keys of {where}: {', '.join(map(str, options))}." if options else ""
    return ConfigError(
        f"{_given(str(key)) or key}: the config has no key '{key}'{near}.{shown} Fix the "
        f"spelling (`{command} --cfg job` prints every key of the composed config); "
        f"`+{key}=<value>` adds a key, which only a component that takes it can use.")


def _no_group(group: str, command: str) -> ConfigError:
    stage = "ea" if group.endswith("density_field") else "rte"
    return ConfigError(
        f"{_given(group) or group}: this composition has no config group '{group}' to "
        f"choose from (sub-groups belong to the configs that list them: model/density_field "
        f"to stage=ea, model/light_field and model/medium to stage=rte and stage=forward). "
        f"Pick the stage first (`{command} stage={stage} {group}=<option>`), or see "
        f"`{command} --help` for the groups.")


def _missing_option(exc: MissingConfigException, command: str) -> ConfigError:
    missing = str(exc.missing_cfg_file)
    if not exc.options:
        return ConfigError(f"no config '{missing}' in conf/: {_paragraph(exc)}. Check "
                           f"--config-name, or reinstall nrt from its source checkout.")
    group, _, option = missing.rpartition("/")
    why = "" if _given(group) else (
        f" No override chose it: a config you picked (a stage or an experiment) names "
        f"{group}={option} in its defaults, so that combination does not exist (e.g. "
        f"experiment=rte_paper goes with stage=rte or stage=forward)."
    )
    return ConfigError(
        f"{group}={option}: config group '{group}' has no option '{option}'"
        f"{_close(option, exc.options)}; its options are {', '.join(exc.options)} "
        f"(conf/{group}/).{why}")


def _bad_override(exc: OverrideParseException, command: str) -> ConfigError:
    detail = _paragraph(re.sub(r"\s*expecting \{.*?\}", "", str(exc.message)))
    detail = re.sub(r"^Error parsing override '.*?'\s*", "", detail)
    return ConfigError(
        f"cannot read the override '{exc.override}' ({detail}). An override is key=value "
        f"(+key=value adds a key, ~key removes one) or group=option; quote values with "
        f"spaces or brackets ('key=\"a b\"'). `{command} --help` lists the config groups.")


def _call_failed_itself(cause: BaseException) -> bool:
    """Whether ``cause`` was raised by the call into a ``_target_`` (arguments that do not
    fit its signature), not from inside it: its traceback ends in Hydra's frame."""
    tb: types.TracebackType | None = cause.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb is not None and "hydra" in tb.tb_frame.f_code.co_filename


def _instantiation(exc: InstantiationException, command: str) -> NrtError | None:
    cause = exc.__cause__
    if isinstance(cause, NrtError):
        return cause
    found = re.search(r"full_key: (\S+)", str(exc))
    key = found.group(1) if found else "the config"
    target = re.search(r"target '([^']+)'", str(exc))
    target = target.group(1) if target else "its _target_"
    if isinstance(cause, ImportError):
        return ConfigError(
            f"{key}._target_={target}: cannot import it ({_paragraph(cause)}). A `_target_` "
            f"names a class or function by its module path (nrt.modules.<module>.<Class>); "
            f"fix it in the config file or the override (`{command} --cfg job` shows it).")
    if isinstance(cause, TypeError) and _call_failed_itself(cause):
        return ConfigError(
            f"{key}: {target} cannot be built from the keys of {key} ({cause}). The keys "
            f"beside `_target_` are its arguments: remove or rename the key (`{command} --cfg "
            f"job` shows them), or choose a config whose `_target_` takes it.")
    return None


def _raised_by_nrt(exc: BaseException) -> NrtError | None:
    """The :class:`NrtError` that nrt's own resolver raised while OmegaConf resolved an
    interpolation (``${nrt_run_dir:...}`` refusing a scene name), which OmegaConf wraps."""
    seen = exc.__cause__ or exc.__context__
    while isinstance(seen, InterpolationResolutionError):
        seen = seen.__cause__ or seen.__context__
    return seen if isinstance(seen, NrtError) and \
        isinstance(exc, InterpolationResolutionError) else None


def config_mistake(exc: BaseException, command: str) -> NrtError | None:
    """``exc`` as the user's config mistake (a :class:`ConfigError` naming the key and the
    fix; a component's own :class:`NrtError` unwrapped from Hydra's instantiation error),
    or None when it is not one. ``command`` (``nrt-train``) appears in the hints. Of
    OmegaConf's own errors only values that cannot be resolved count: a missing key read by
    nrt's code is a bug."""
    if isinstance(exc, NrtError):
        return exc
    raised = _raised_by_nrt(exc)
    if raised is not None:
        return raised
    if isinstance(exc, InstantiationException):
        return _instantiation(exc, command)
    if isinstance(exc, OverrideParseException):
        return _bad_override(exc, command)
    if isinstance(exc, MissingConfigException):
        return _missing_option(exc, command)
    if isinstance(exc, ConfigCompositionException):
        if isinstance(exc.__cause__, ConfigKeyError | ConfigAttributeError):
            return _unknown_key(exc.__cause__, command)
        no_group = re.match(r"Could not override '([^']+)'\. No match in the defaults list",
                            str(exc))
        if no_group:
            return _no_group(no_group.group(1), command)
        deleted = re.match(r"Could not delete from config\. '([^']+)' does not exist", str(exc))
        if deleted:
            key = deleted.group(1)
            return ConfigError(f"~{key}: the config has no key '{key}' to remove. Check the "
                               f"spelling against `{command} --cfg job`, which prints every key.")
        return ConfigError(f"{_paragraph(exc)}. Check the override against `{command} --cfg "
                           "job`, which prints the composed config.")
    if isinstance(exc, InterpolationResolutionError | MissingMandatoryValue | GrammarParseError):
        key = getattr(exc, "full_key", None) or "the config"
        return ConfigError(
            f"{key}: {_paragraph(getattr(exc, 'msg', None) or exc)}. Fix the value: an "
            f"interpolation ${{...}} must name a key the config has, and a key left ??? must "
            f"be given (`{command} --cfg job` prints the composed config).")
    return None
