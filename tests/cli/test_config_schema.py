"""The typed settings (nrt/cli/schema.py): a value of the wrong type or an unknown key under
``scene.effects``, ``losses.samples``, ``model.lr``, ``model.sun``, ``model.coupling``,
``init``, ``model.density`` or ``render`` is refused while the config is composed, with a
one-paragraph ``nrt: error:`` naming the key, what was given, what the key takes and the fix, exit
status 2 and nothing written; values a type cannot judge (a negative rate) are left to the
component. A method named by ``method=<name>`` (conf/method) composes as the stage, mode and
experiment it stands for."""

from __future__ import annotations

import dataclasses
import re
import sys
from pathlib import Path

import hydra
import pytest
from hydra.errors import InstantiationException
from omegaconf import MISSING, OmegaConf

from nrt.cli.common import CONFIG_DIR
from nrt.cli.config_errors import config_mistake
from nrt.cli.schema import SCHEMAS, check_schema_keys, field_doc, field_names
from nrt.errors import ConfigError
from tests.conftest import cli_in_process, compose_config, refusal

TYPED = ("scene", "losses", "model", "init", "render")
"""The roots that hold typed settings (resolved here as nrt-train resolves the config)."""

pytestmark = pytest.mark.integration


def resolve_typed(cfg) -> None:
    """Resolve the roots of :data:`TYPED` (the rest reads Hydra's run-time keys)."""
    for root in TYPED:
        OmegaConf.to_container(cfg[root], resolve=True)


def refusal_of(overrides: tuple[str, ...], monkeypatch: pytest.MonkeyPatch) -> str:
    """The message nrt-train gives ``overrides`` (``preset=tiny``), in-process: the
    composition, the resolution of the typed settings and :func:`check_schema_keys`, each
    failure worded by :func:`config_mistake`."""
    monkeypatch.setattr(sys, "argv", ["nrt-train", *overrides])
    try:
        cfg = compose_config("train", ["preset=tiny", *overrides])
        resolve_typed(cfg)
        check_schema_keys(cfg)
    except Exception as exc:  # noqa: BLE001 - what nrt-train meets, as it meets it
        mistake = config_mistake(exc, "nrt-train")
        assert isinstance(mistake, ConfigError), exc
        return str(mistake)
    raise AssertionError(f"{overrides} were not refused")


MISTAKES = [  # (overrides, what the message must say)
    (("scene.effects.chromatic=maybe",),
     "scene.effects.chromatic=maybe: must be true or false (true: RGB extinction"),
    (("scene.effects.max_scattering_order=1.5",),
     "scene.effects.max_scattering_order=1.5: must be a whole number (scattering orders"),
    (("scene.effects.phase=[hg]",), "scene.effects.phase=[hg]: must be a string"),
    (("scene.effects.emitters=[{position:[0,0,0],intensity:[1,1,1],power:3}]",),
     "an entry of scene.effects.emitters has no key 'power'; it holds a point light: "
     "position, intensity"),
    (("scene.effects.emitters=[{position:[0,0,up],intensity:[1,1,1]}]",),
     "position[2] must be a number (where the light is"),
    (("stage=rte", "losses.samples.photo_rayz=3"),
     "losses.samples.photo_rayz=3: losses.samples has no key 'photo_rayz' (did you mean "
     "'photo_rays'?); it holds the objectives' sample counts: photo_rays, vre_samples"),
    (("stage=rte", "+losses.samples.photo_rayz=3"),
     "+losses.samples.photo_rayz: losses.samples has no key 'photo_rayz'"),
    (("stage=rte", "losses.samples.vre_samples=many"),
     "losses.samples.vre_samples=many: must be a whole number (jittered strata per camera ray"),
    (("stage=rte", "budget.rte.vre_samples=1.5"),
     "budget.rte.vre_samples=1.5: must be a whole number (jittered strata per camera ray of "
     "the volume rendering equation), as losses.samples.vre_samples reads it"),
    (("stage=rte", "experiment=rte_paper", "losses.samples.env_fraction=half"),
     "losses.samples.env_fraction=half: must be a number (share of inflow directions"),
    (("stage=rte", "model.lr.light=fast"),
     "model.lr.light=fast: must be a number (rate of the scattered-light field"),
    (("stage=rte", "model.lr.ligth=0.01"),
     "model.lr.ligth=0.01: model.lr has no key 'ligth' (did you mean 'light'?); it holds one "
     "learning rate per part: light, medium"),
    (("stage=rte", "+model.lr.ligth=0.01"), "+model.lr.ligth: model.lr has no key 'ligth'"),
    (("stage=rte", "experiment=rte_paper", "~model.lr.density"),
     "~model.lr.density: model.lr takes one learning rate per part, light, medium, density; "
     "density missing"),
    (("stage=rte", "model.sun.max_suns=[4]"), "model.sun.max_suns=[4]: must be a whole number"),
    (("stage=rte", "model.coupling.adjoint=maybe"),
     "model.coupling.adjoint=maybe: must be true or false (true: an adjoint SH grid"),
    (("stage=rte", "+model.coupling.adjiont=true"),
     "model.coupling has no key 'adjiont' (did you mean 'adjoint'?)"),
    (("stage=rte", "init.train=sometimes"), "init.train=sometimes: must be true or false"),
    (("stage=rte", "init=oracle", "init.truth_share=half"),
     "init.truth_share=half: must be a number (the truth's share"),
    (("stage=dpt", "init=grids", "init.grids=[a.npz]"),
     "init.grids=[a.npz]: must be a string or null (path of a property-grid .npz file"),
    (("stage=forward", "model.density.source=[ea]"),
     "model.density.source=[ea]: must be a string"),
    (("render.progress=maybe",), "render.progress=maybe: must be true or false (true: a "
     "progress bar while rendering)"),
    (("render.variant=[1]",), "render.variant=[1]: must be a string (variant of Mitsuba"),
    (("render.varient=scalar_rgb",), "render.varient=scalar_rgb: render has no key 'varient' "
     "(did you mean 'variant'?); it holds the render settings: variant, progress"),
]


@pytest.mark.parametrize(("overrides", "needle"), MISTAKES,
                         ids=[" ".join(m[0]) for m in MISTAKES])
def test_a_typed_setting_refuses_a_wrong_type_or_key_naming_it(overrides, needle, monkeypatch):
    message = refusal_of(overrides, monkeypatch)
    assert needle in message and "\n" not in message, message
    assert "--cfg job" in message or "Drop the override" in message, message


def test_a_config_file_with_a_wrong_type_is_named_in_the_fix(tmp_path, monkeypatch):
    """A mistake in a config file (here an ablation of its own, on Hydra's search path)
    names the key and the file to fix."""
    (tmp_path / "ablation").mkdir()
    (tmp_path / "ablation" / "bad.yaml").write_text(
        "# @package _global_\nlosses:\n  samples:\n    photo_rays: many\n")
    message = refusal_of(("stage=rte", f"hydra.searchpath=[file://{tmp_path}]",
                          "ablation=bad"), monkeypatch)
    assert message.startswith("losses.samples.photo_rays=many: must be a whole number"), message
    assert "Fix it in conf/ablation/bad.yaml" in message


def test_values_a_type_cannot_judge_are_left_to_the_component():
    """A negative rate is a number: the schema lets it through and the stage refuses it
    (a ConfigError naming the key, before any data), as it does outside nrt-train."""
    cfg = compose_config("train", ["preset=tiny", "stage=rte", "init=none", "model.lr.light=-1"])
    check_schema_keys(cfg)
    with pytest.raises(ConfigError, match=re.escape("model.lr.light=-1.0: a learning rate")):
        try:
            hydra.utils.instantiate(cfg.model, _convert_="all")
        except InstantiationException as exc:  # as nrt.cli.common.run_app unwraps it
            raise exc.__cause__ from None


@pytest.mark.parametrize("overrides", [
    ("scene.effects.emitters=null",), ("stage=rte", "model.sun.threshold=null"),
    ("stage=rte", "init.ea_ckpt=some/last.ckpt"), ("stage=rte", "scene=isotropic"),
    ("stage=rte", "experiment=rte_paper", "init.train=true"), ("stage=dpt", "init=grids"),
    ("scene.effects.emitters=[{position:[0,0.5,0],intensity:[2,2,2]}]",)])
def test_values_of_the_right_type_pass(overrides):
    cfg = compose_config("train", ["preset=tiny", *overrides])
    resolve_typed(cfg)
    check_schema_keys(cfg)


@pytest.mark.parametrize("schema", SCHEMAS.values(), ids=list(SCHEMAS))
def test_every_field_has_a_type_a_meaning_and_no_default(schema):
    """The config files hold the values; a schema adds types and meanings, no key."""
    for field in dataclasses.fields(schema):
        assert field.default is MISSING, (schema, field.name)
        assert field_doc(schema, field.name).strip(), (schema, field.name)
    assert schema.what and field_names(schema)


def test_every_schema_is_named_by_a_config_file_and_every_name_is_stored():
    named = {m for path in CONFIG_DIR.rglob("*.yaml")
             for m in re.findall(r"^\s*- /schema/(\w+)@", path.read_text(), re.M)}
    assert named == set(SCHEMAS), named ^ set(SCHEMAS)


def test_a_typed_node_holds_exactly_its_schema_keys():
    for overrides in (("stage=rte", "init=oracle"), ("stage=rte", "experiment=rte_paper"),
                      ("stage=forward",), ("stage=dpt", "init=grids")):
        cfg = compose_config("train", ["preset=tiny", *overrides])
        for key in ("scene.effects", "losses.samples", "model.lr", "model.sun",
                    "model.coupling", "init", "model.density", "render"):
            node = OmegaConf.select(cfg, key)
            if OmegaConf.is_dict(node):  # dpt's model.lr is one number
                assert list(node) == field_names(OmegaConf.get_type(node)), (overrides, key)


@pytest.mark.parametrize(("config", "override", "needle"), [
    ("dataset", "render.progress=maybe", "render.progress=maybe: must be true or false"),
    ("eval", "render.variant=[1]", "render.variant=[1]: must be a string (variant of Mitsuba"),
    ("sample", "render.views=four", "render.views=four: must be a whole number or null "
     "(held-out cameras"),
    ("sample", "render.progress=false", "render.progress=false: render has no key 'progress'"),
])
def test_every_command_types_its_render_settings(config, override, needle, monkeypatch):
    """nrt-data, nrt-eval and nrt-sample refuse a mistyped or unknown render key as
    nrt-train does (nrt-sample's render settings are its own: views and spp, no bar)."""
    monkeypatch.setattr(sys, "argv", [f"nrt-{config}", override])
    try:
        compose_config(config, [override])
    except Exception as exc:  # noqa: BLE001 - worded as the command words it
        message = str(config_mistake(exc, f"nrt-{config}"))
        assert message.startswith(needle) and "\n" not in message, message
    else:
        raise AssertionError(f"{config}: {override} was not refused")


CLI_MISTAKES = [  # (overrides of nrt-train, what the message must say)
    pytest.param(("scene.effects.chromatic=maybe",),
                 "nrt: error: scene.effects.chromatic=maybe: must be true or false"),
    pytest.param(("stage=rte", "+model.lr.ligth=0.01"),
                 "nrt: error: +model.lr.ligth: model.lr has no key 'ligth'",
                 marks=pytest.mark.slow),
    pytest.param(("stage=rte", "budget.rte.vre_samples=1.5"),
                 "nrt: error: budget.rte.vre_samples=1.5: must be a whole number",
                 marks=pytest.mark.slow),
]


@pytest.mark.parametrize(("overrides", "needle"), CLI_MISTAKES)
def test_schema_mistakes_end_in_one_paragraph_and_status_2(tmp_path: Path, overrides, needle):
    """Through the command (composition, resolution and the key check; in the test's
    process, :func:`~tests.conftest.cli_in_process`): status
    2, one ``nrt: error:`` paragraph, no traceback, nothing written."""
    out, data = tmp_path / "out", tmp_path / "datasets"
    out.mkdir()
    proc = cli_in_process("train", "preset=tiny", f"paths.data_dir={data}", *overrides,
                          env={"NRT_OUTPUT_DIR": str(out)})
    assert refusal(proc.returncode, proc.stderr).startswith(needle), proc.stderr[-2000:]
    assert list(out.iterdir()) == [] and not data.exists()


# ------------------------------------------------------------------------------ methods
METHODS = {  # conf/method/<name>.yaml -> the command line it stands for
    "ea": ("stage=ea",),
    "rte": ("stage=rte",),
    "rte_paper": ("stage=rte", "experiment=rte_paper"),
    "dpt": ("stage=dpt",),
    "forward": ("stage=forward",),
    "forward_paper": ("stage=forward", "experiment=rte_paper"),
    "generative_ea": ("stage=ea", "mode=generative", "scene=family"),
    "generative_rte": ("stage=rte", "mode=generative", "scene=family"),
}


def test_every_method_is_listed():
    assert sorted(p.stem for p in (CONFIG_DIR / "method").glob("*.yaml")) == sorted(METHODS)


@pytest.mark.parametrize("method", METHODS)
def test_a_method_composes_as_the_command_line_it_names(method):
    by_name = compose_config("train", ["preset=tiny", f"method={method}"])
    spelt = compose_config("train", ["preset=tiny", *METHODS[method]])
    assert OmegaConf.to_container(by_name) == OmegaConf.to_container(spelt)


@pytest.mark.parametrize(("with_method", "spelt"), [
    (("method=rte_paper", "stage=forward"), ("stage=forward", "experiment=rte_paper")),
    (("method=rte_paper", "experiment=ea_tensorboard_and_csv"),
     ("stage=rte", "experiment=rte_paper", "logger=[tensorboard,csv]")),
    (("method=rte", "experiment=accuracy_vs_time"), ("experiment=accuracy_vs_time",)),
])
def test_groups_on_the_command_line_and_recipes_combine_with_a_method(with_method, spelt):
    """A group named on the command line wins over the method's choice, and the experiment
    group stays free for recipes."""
    by_name = compose_config("train", ["preset=tiny", *with_method])
    assert OmegaConf.to_container(by_name) == \
        OmegaConf.to_container(compose_config("train", ["preset=tiny", *spelt]))
