"""A scene's declared effects decide which terms the renderer builds, and nothing else."""

import numpy as np
import pytest

from nrt.mitsuba.render import ViewRenderer
from nrt.mitsuba.scene import mitsuba_properties, scene_dict
from nrt.mitsuba.variant import select_variant

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def mi():
    return select_variant()


def spec(phase="hg", chromatic=True, order=-1, emitters=()):
    return {"bbox": [[-1, -1, -1], [1, 1, 1]],
            "effects": {"phase": phase, "chromatic": chromatic, "max_scattering_order": order,
                        "emitters": list(emitters)},
            "medium": {"elements": [{"g": 0.3}]}}


def grids(n=4):
    rng = np.random.default_rng(0)
    return {"sigma_a": rng.uniform(0, 1, (n, n, n, 3)).astype(np.float32),
            "sigma_s": rng.uniform(0, 1, (n, n, n, 3)).astype(np.float32),
            "g": np.full((n, n, n), 0.3, np.float32)}


def build(mi, s):
    return scene_dict(mi, s, grids(), np.ones((8, 16, 3), np.float32), 8, 8,
                                      40.0, 4)


@pytest.mark.parametrize("phase,plugin", [("isotropic", "isotropic"), ("hg", "hg"),
                                          ("varying_hg", "nrt_hg_grid")])
def test_phase_plugin_follows_effects(mi, phase, plugin):
    medium = build(mi, spec(phase=phase))["medium_box"]["interior"]
    assert medium["phase"]["type"] == plugin
    assert ("g" in medium["phase"]) == (phase != "isotropic")
    if phase == "hg":
        assert medium["phase"]["g"] == pytest.approx(0.3)


@pytest.mark.parametrize("chromatic,channels", [(True, 3), (False, 1)])
def test_grey_extinction_builds_one_channel(mi, chromatic, channels):
    medium = build(mi, spec(chromatic=chromatic))["medium_box"]["interior"]
    assert medium["sigma_t"]["grid"].channel_count() == channels
    assert medium["albedo"]["grid"].channel_count() == 3


def test_grey_scene_warns_about_grids_that_are_not_grey(caplog):
    """Grey extinction is one sigma_t with an RGB albedo: grey grids (sigma_a + sigma_s
    equal in R, G, B, coloured albedo) pass silently; grids whose extinction differs
    between channels get a warning that only channel 0's sigma_t is rendered."""
    g = grids()
    t = g["sigma_a"][..., :1] + g["sigma_s"][..., :1]
    albedo = np.array([0.9, 0.5, 0.2], np.float32)
    grey = {"sigma_a": t * (1 - albedo), "sigma_s": t * albedo, "g": g["g"]}
    effects = spec(chromatic=False)["effects"]
    with caplog.at_level("WARNING", logger="nrt.mitsuba.scene"):
        props = mitsuba_properties(grey, effects)
    assert not caplog.records
    np.testing.assert_allclose(props["albedo"][t[..., 0] > 0], np.broadcast_to(
        albedo, props["albedo"][t[..., 0] > 0].shape), rtol=1e-5)
    mitsuba_properties(g, effects)
    assert "channel 0" in caplog.text


@pytest.mark.parametrize("order,depth", [(-1, -1), (0, 1), (1, 2), (5, 6)])
def test_scattering_order_sets_max_depth(mi, order, depth):
    assert build(mi, spec(order=order))["integrator"]["max_depth"] == depth


def test_point_lights_only_when_listed(mi):
    assert not [k for k in build(mi, spec()) if k.startswith("point_light")]
    lights = [{"position": [0, 3, 0], "intensity": [5, 4, 3]}]
    scene = build(mi, spec(emitters=lights))
    assert scene["point_light_0"]["type"] == "point"
    # and it renders: the point light adds light to the medium
    dark = ViewRenderer(mi, build(mi, spec())).render(
        _front_camera(), 8, 0)
    lit = ViewRenderer(mi, scene).render(_front_camera(), 8, 0)
    assert lit.mean() > dark.mean()


def _front_camera():
    from nrt.cameras import look_at

    return look_at([0, 0, 4.0], [0, 0, 0])
