"""Config mistakes as nrt's one-paragraph errors.

Hydra and OmegaConf report a mistake on the command line or in the config tree with their
own exceptions: an unknown key or group option, an override they cannot parse, a key
deleted that is not there, an interpolation that names no key, a ``_target_`` that cannot
be imported or called with the keys its config holds, a value of the wrong type or a
misspelt key under a typed setting (:mod:`nrt.cli.schema`). :func:`config_mistake` turns each
into a :class:`~nrt.errors.ConfigError` that names the key and the fix, which the commands
print as ``nrt: error: ...`` with exit status 2 (:func:`nrt.cli.common.run_app`). Any
other exception is left alone: a bug keeps its traceback.
"""

from __future__ import annotations

import difflib
import re
import sys
import types
from collections.abc import Mapping

from hydra.errors import (
    ConfigCompositionException,
    InstantiationException,
    MissingConfigException,
    OverrideParseException,
)
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import (
    ConfigAttributeError,
    ConfigKeyError,
    ConfigTypeError,
    GrammarParseError,
    InterpolationResolutionError,
    MissingMandatoryValue,
    ValidationError,
)

from nrt.cli.schema import expected, field_names, field_of, is_schema, unknown_key_error
from nrt.errors import ConfigError, NrtError


def value_text(value: object) -> str:
    """``value`` as an override writes it (``null``, ``{a: 1}``, ``[4, 8]``)."""
    if value is None:
        return "null"
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{k}: {value_text(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(value_text(v) for v in value) + "]"
    return str(value)


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


def _config_file(exc: BaseException) -> str | None:
    """The config file that Hydra was merging when ``exc`` happened (``conf/<name>.yaml``),
    from its ``In '<name>': ...`` message; None for an override."""
    found = re.match(r"In '([^']+)'", str(exc))
    return f"conf/{found.group(1)}.yaml" if found else None


def _fix(exc: BaseException | None, what: str) -> str:
    """``Fix <what> in the config file`` Hydra was merging, else ``Fix the override``."""
    where = _config_file(exc) if exc is not None else None
    return f"Fix {what} in {where}" if where else "Fix the override"


def _unknown_key(exc: ConfigKeyError | ConfigAttributeError, command: str,
                 composing: BaseException | None = None) -> ConfigError:
    key = exc.full_key or exc.key
    parent = exc.parent_node
    schema = OmegaConf.get_type(parent) if isinstance(parent, DictConfig) else None
    if is_schema(schema) and str(exc.key) not in field_names(schema):
        found = re.match(r"Could not override '([^']+)'", str(composing or ""))
        override = found.group(1) if found else "the list"
        owner = str(key).rsplit(".", 1)[0] if "." in str(key) else f"an entry of {override}"
        shown = _given(str(key)) or _given(override) or str(key)
        return unknown_key_error(owner, str(exc.key), schema, shown,
                                 f"{_fix(composing, 'the spelling')} (`{command} --cfg job` "
                                 "prints every key).")
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
        f" No override chose it: a config you picked (a stage, a method or an experiment) names "
        f"{group}={option} in its defaults, so that combination does not exist (e.g. "
        f"experiment=rte_paper goes with stage=rte or stage=forward)."
    )
    if group == "hydra/launcher":  # nrt's presets name the plugins' configs
        why = (" Hydra's joblib and submitit launchers come with nrt's `scale` extra: pip "
               "install -e '.[scale]'.")
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


def _wrong_type(exc: ValidationError, command: str, composing: BaseException | None
                ) -> ConfigError:
    """A value that the schema of its key (:mod:`nrt.cli.schema`) does not admit: the
    override (or the key an interpolation reads it from), what the key takes and means,
    and the fix."""
    hint, doc = field_of(exc.parent_node, exc.key)
    key, value = str(exc.full_key or exc.key), value_text(exc.value)
    want = (expected(hint) if hint is not None else "of its schema's type") + \
        (f" ({doc[:1].lower()}{doc[1:].rstrip('.')})" if doc else "")
    override = re.match(r"Error merging override (.+)", str(composing or ""))
    link = _read_from(exc) if isinstance(exc, InterpolationResolutionError) else None
    if link is not None:
        text = f"{_given(link) or f'{link}={value}'}: must be {want}, as {key} reads it"
    elif override is not None:
        given = override.group(1).strip()
        named = given.split("=", 1)[0].lstrip("+~")
        text = f"{given}: must be {want}" if named == key else \
            f"{given}: {key} must be {want}, not {value}"
    else:
        text = f"{key}={value}: must be {want}"
    return ConfigError(f"{text}. {_fix(composing, 'it')}; `{command} --cfg job` prints the "
                       "composed config.")


def _read_from(exc: ValidationError) -> str | None:
    """The key that the failing node's interpolation ``${key}`` names, if it is one."""
    parent = exc.parent_node
    node = parent._get_node(exc.key) if isinstance(parent, DictConfig) else None
    raw = node._value() if node is not None else None
    found = re.fullmatch(r"\$\{([\w.]+)\}", raw) if isinstance(raw, str) else None
    return found.group(1) if found else None


def _removed(exc: ConfigTypeError, command: str) -> ConfigError:
    """``~key`` of a key that its schema requires."""
    parent, name = str(exc.full_key).rsplit(".", 1)
    schema = OmegaConf.get_type(exc.parent_node)
    return ConfigError(
        f"~{exc.full_key}: {parent} takes {schema.what}, {', '.join(field_names(schema))}; "
        f"{name} missing, it is incomplete. Set {exc.full_key}=<value> instead of removing it "
        f"(`{command} --cfg job` prints the composed config).")


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
    if isinstance(exc, ValidationError):  # a typed key reading a value of another type
        return _wrong_type(exc, command, None)
    if isinstance(exc, ConfigCompositionException):
        cause = exc.__cause__ or exc.__context__  # a config file's mistake comes as context
        if isinstance(cause, ConfigKeyError | ConfigAttributeError):
            return _unknown_key(cause, command, exc)
        if isinstance(cause, ValidationError):
            return _wrong_type(cause, command, exc)
        if isinstance(cause, ConfigTypeError) and "deletion" in str(cause) and \
                isinstance(cause.parent_node, DictConfig):
            return _removed(cause, command)
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
