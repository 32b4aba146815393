"""Typed schemas of the dict-shaped settings, checked by Hydra as it composes the config.

Each dataclass below is stored in Hydra's ConfigStore as ``schema/<name>`` (:data:`SCHEMAS`)
and named in the defaults list of the config files that hold the setting, e.g.
``- /schema/effects@effects`` in ``conf/scene/default.yaml``, so that a value of the wrong
type or a misspelt key in a config file or an override is refused while the config is
composed, before anything is built or loaded (:mod:`nrt.cli.config_errors` words the
error). The config files keep the values; a schema gives each key its type and meaning
(the docstring under each field, which the error messages quote) and no defaults, so it
adds no key. What a type cannot say (ranges, names from a list, cross-key rules) the
components and :mod:`nrt.cli.checks` check.

Keys added with ``+key=value`` pass the composition; :func:`check_schema_keys` refuses them.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import functools
import inspect
import types
import typing
from dataclasses import dataclass
from typing import ClassVar

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf

from nrt.errors import ConfigError


@dataclass
class Emitter:
    """A point light of a scene (``scene.effects.emitters``)."""

    what: ClassVar[str] = "a point light"
    position: list[float] = MISSING
    """Where the light is, [x, y, z] in world units."""
    intensity: list[float] = MISSING
    """Radiant intensity, linear RGB [r, g, b] (radiance times squared world units)."""


@dataclass
class Effects:
    """The effects a scene declares (``scene.effects``, conf/scene/default.yaml)."""

    what: ClassVar[str] = "the scene's effects"
    phase: str = MISSING
    """Phase function: isotropic, hg with one shared g, or varying_hg with a g field."""
    chromatic: bool = MISSING
    """True: RGB extinction; false: one grey sigma_t, equal in R, G and B, with an RGB albedo."""
    max_scattering_order: int = MISSING
    """Scattering orders rendered in the photos: -1 all, 0 attenuation only, 1 single, ..."""
    emitters: list[Emitter] | None = MISSING
    """Point lights inside the scene: a list of {position, intensity}; [] or null for none."""


@dataclass
class SplitSamples:
    """Sample counts of the split stage 2's objectives (``losses.samples``,
    conf/losses/rte.yaml)."""

    what: ClassVar[str] = "the objectives' sample counts"
    photo_rays: int = MISSING
    """Photo rays per step, the first of each ray batch."""
    vre_samples: int = MISSING
    """Jittered strata per camera ray of the volume rendering equation."""
    sky_env_directions: int = MISSING
    """Shadow rays per sample drawn from the sky (multiple importance sampling; 0: none)."""
    sky_phase_directions: int = MISSING
    """Shadow rays per sample drawn from the phase function (0: none)."""
    shadow_steps: int = MISSING
    """Jittered strata of each shadow ray toward suns and emitters."""
    transport_points: int = MISSING
    """Points (each with one direction) of the transport objective per step."""
    transport_samples: int = MISSING
    """Strata of the transport objective's backward march."""
    uncollided_every: int = MISSING
    """Training steps between refreshes of the uncollided light's cache."""
    uncollided_directions: int = MISSING
    """Sky directions per cache cell of a refresh."""
    uncollided_blend: float = MISSING
    """Weight of a refresh in the cache's moving average, in (0, 1]."""
    uncollided_shared: bool = MISSING
    """True: the skies of one medium share the refresh's shadow rays (multiple importance
    sampling over their samplers); false: each sky draws its own."""


@dataclass
class PaperSamples:
    """Sample counts of the paper's stage-2 objectives (``losses.samples``,
    conf/losses/rte_paper.yaml)."""

    what: ClassVar[str] = "the objectives' sample counts"
    collocation_points: int = MISSING
    """Points of the RTE residual per step."""
    density_fraction: float = MISSING
    """Share of the collocation points drawn like the extinction, in [0, 1]."""
    density_grid: int = MISSING
    """Cells per axis of the grid that the extinction-like draws follow."""
    inscatter_directions: int = MISSING
    """In-scattering directions per collocation point (per estimate)."""
    boundary_points: int = MISSING
    """Points on the box's faces of the boundary objective per step."""
    env_fraction: float = MISSING
    """Share of inflow directions drawn like the environment, in [0, 1]."""
    vre_rays: int = MISSING
    """Camera rays per step rendered by the volume rendering equation."""
    vre_samples: int = MISSING
    """Strata per such ray."""
    vre_directions: int = MISSING
    """In-scattering directions per VRE sample (per estimate)."""
    shadow_steps: int = MISSING
    """Midpoint steps of shadow rays to emitters and suns."""


@dataclass
class SplitRates:
    """Adam's learning rates of the split stage 2 (``model.lr``, conf/model/rte.yaml)."""

    what: ClassVar[str] = "one learning rate per part"
    light: float = MISSING
    """Rate of the scattered-light field, whose SH coefficients are in units of radiance_scale."""
    medium: float = MISSING
    """Rate of the medium's modulation: its extinction exponents and albedo logits."""


@dataclass
class PaperRates(SplitRates):
    """Adam's learning rates of the paper's stage 2 (``model.lr``,
    conf/model/rte_paper.yaml)."""

    density: float = MISSING
    """Rate of the EA density field, which init.train=true fine-tunes."""


@dataclass
class Sun:
    """The explicit first scattering of the environment's sun (``model.sun``)."""

    what: ClassVar[str] = "the sun's settings"
    threshold: float | None = MISSING
    """Texels brighter than this times the mean radiance become suns; null: no sun."""
    max_suns: int = MISSING
    """Most directional lights split off the environment map."""


@dataclass
class Coupling:
    """Gradients of the photos through the scattered light (``model.coupling``,
    conf/model/rte.yaml; docs/stage2.md)."""

    what: ClassVar[str] = "the coupling's settings"
    unrolled_directions: int = MISSING
    """Directions per camera sample of one source-iteration step unrolled with gradient; 0: off."""
    unrolled_samples: int = MISSING
    """Strata of that step's march."""
    adjoint: bool = MISSING
    """True: an adjoint SH grid carries the photos' gradient to the medium."""
    adjoint_blend: float = MISSING
    """Weight of a step's photo gradient in the adjoint's source, in (0, 1]."""


@dataclass
class Start:
    """Where stage 2's and the baseline's density comes from (the ``init`` group, read
    as ``model.density``)."""

    what: ClassVar[str] = "the density start"
    source: str = MISSING
    """ea: an EA run; none; oracle: the true extinction; grids: stage=dpt only; ground_truth."""
    ea_ckpt: str | None = MISSING
    """Path of the EA checkpoint to start from; null: the scene's newest EA run."""
    train: bool = MISSING
    """True: the EA density is fine-tuned with the stage at model.lr.density; false: frozen."""


@dataclass
class GridsStart(Start):
    """A start from property grids (``init=grids``, stage=dpt only)."""

    grids: str | None = MISSING
    """Path of a property-grid .npz file with sigma_a, sigma_s and g (a run's medium_grids.npz)."""


@dataclass
class OracleStart(Start):
    """A start from the dataset's true extinction (``init=oracle``, a diagnostic)."""

    truth_share: float = MISSING
    """The truth's share a of the start EA^(1 - a) truth^a, in [0, 1]; 1: the truth alone."""


@dataclass
class Render:
    """How a command renders with Mitsuba (``render``, conf/train.yaml, conf/dataset.yaml,
    conf/eval.yaml)."""

    what: ClassVar[str] = "the render settings"
    variant: str = MISSING
    """Variant of Mitsuba: auto, llvm_ad_rgb, cuda_ad_rgb, scalar_rgb; NRT_MITSUBA_VARIANT wins."""
    progress: bool = MISSING
    """True: a progress bar while rendering."""


@dataclass
class SampleRender:
    """How nrt-sample renders its media (``render``, conf/sample.yaml): the variant as
    :class:`Render`'s, then its own counts."""

    what: ClassVar[str] = "the render settings"
    variant: str = MISSING
    """Variant of Mitsuba, as nrt-train's ``render.variant``."""
    views: int | None = MISSING
    """Held-out cameras of the family per sky; null: all."""
    spp: int | None = MISSING
    """Samples per pixel; null: the family's."""


SCHEMAS: dict[str, type] = {
    "effects": Effects, "split_samples": SplitSamples, "paper_samples": PaperSamples,
    "split_rates": SplitRates, "paper_rates": PaperRates, "sun": Sun, "coupling": Coupling,
    "start": Start, "grids_start": GridsStart, "oracle_start": OracleStart,
    "render": Render, "sample_render": SampleRender,
}
"""Name in the ConfigStore's ``schema`` group -> schema, as the config files name them."""


def register_schemas() -> None:
    """Store every schema of :data:`SCHEMAS` as ``schema/<name>`` in Hydra's ConfigStore;
    done when this module is imported (:mod:`nrt.cli.common` imports it), before any
    composition of conf/."""
    store = ConfigStore.instance()
    for name, node in SCHEMAS.items():
        store.store(group="schema", name=name, node=node, provider="nrt")


register_schemas()


@functools.cache
def _field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of ``cls`` and its bases, by field name."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__[:-1]):
        body = ast.parse(inspect.getsource(klass)).body[0].body
        for node, after in zip(body, body[1:], strict=False):
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and \
                    isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant):
                docs[node.target.id] = str(after.value.value)
    return docs


def field_doc(cls: type, name: str) -> str:
    """The one-line meaning of field ``name`` of schema ``cls`` ('' when it has none)."""
    return _field_docs(cls).get(name, "") if is_schema(cls) else ""


def is_schema(cls: object) -> bool:
    """Whether ``cls`` (a node's type) is one of nrt's schemas."""
    return isinstance(cls, type) and dataclasses.is_dataclass(cls) and \
        cls.__module__ == __name__


def field_names(cls: type) -> list[str]:
    """The keys of schema ``cls``, in order."""
    return [f.name for f in dataclasses.fields(cls)]


def check_schema_keys(node: DictConfig | ListConfig, key: str = "") -> None:
    """Refuse a key that a schema does not have but ``+key=value`` added to a typed node
    (``+model.coupling.adjiont=true``), naming the keys it has, before anything is built."""
    if node._is_none() or node._is_missing() or node._is_interpolation():
        return
    if isinstance(node, ListConfig):
        children = [(f"{key}[{i}]", node._get_node(i)) for i in range(len(node))]
    else:
        schema = OmegaConf.get_type(node)
        known = field_names(schema) if is_schema(schema) else list(node)
        unknown = [name for name in node if name not in known]
        if unknown:
            raise unknown_key_error(key, unknown[0], schema, f"+{key}.{unknown[0]}",
                                    "Drop the override or fix its spelling.")
        children = [(f"{key}.{name}" if key else str(name), node._get_node(name))
                    for name in node]
    for path, child in children:
        if isinstance(child, DictConfig | ListConfig):
            check_schema_keys(child, path)


def unknown_key_error(parent: str, name: str, schema: type, shown: str, fix: str
                      ) -> ConfigError:
    """The error for the key ``name`` that ``schema``, the type of ``parent``, does not
    have; ``shown`` is how the user wrote it, ``fix`` the sentence that says what to do."""
    known = field_names(schema)
    near = difflib.get_close_matches(name, known, n=1)
    hint = f" (did you mean '{near[0]}'?)" if near else ""
    return ConfigError(f"{shown}: {parent} has no key '{name}'{hint}; it holds {schema.what}: "
                       f"{', '.join(known)} (nrt.cli.schema.{schema.__name__}). {fix}")


WORDS = {int: "a whole number", float: "a number", bool: "true or false", str: "a string"}
"""Scalar types of the schemas, as the error messages name them."""


def expected(hint: object) -> str:
    """What a value of the type ``hint`` is, in words (``float | None``: 'a number or
    null')."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        words = [expected(arg) for arg in args if arg is not type(None)]
        return " or ".join(words + (["null"] if type(None) in args else []))
    if origin is list:
        return f"a list, each entry {expected(args[0])}" if args else "a list"
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return f"{hint.what}, a mapping with the keys {', '.join(field_names(hint))}"
    return WORDS.get(hint, getattr(hint, "__name__", str(hint)))


def field_of(parent: object, key: object) -> tuple[object, str]:
    """The type and meaning of ``key`` in ``parent``, a node of a typed config (an entry of
    a typed list takes the list's); ``(None, '')`` where no schema gives them."""
    if isinstance(parent, ListConfig):
        owner = parent._get_parent()
        hint, doc = field_of(owner, parent._key()) if owner is not None else (None, "")
        for arg in (*typing.get_args(hint), hint):
            if typing.get_origin(arg) is list and typing.get_args(arg):
                return typing.get_args(arg)[0], doc
        return None, doc
    schema = OmegaConf.get_type(parent) if isinstance(parent, DictConfig) else None
    if is_schema(schema) and key in field_names(schema):
        return typing.get_type_hints(schema)[key], field_doc(schema, key)
    return None, ""
