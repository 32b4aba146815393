"""Scene specifications and procedural media: determinism, the effects rules, clear errors
for out-of-range keys, and the ground-truth grids' invariants."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from nrt.data.media import medium_grids
from nrt.data.render import camera_rig
from nrt.data.spec import resolve_scene, spec_hash
from nrt.errors import SceneError

pytestmark = pytest.mark.unit


def sigma_t(element: dict) -> np.ndarray:
    return np.asarray(element["sigma_a"]) + np.asarray(element["sigma_s"])


def blob(**kw) -> dict:
    """An explicit element: a smooth ball with no surface noise."""
    return {"center": [0.0, 0.0, 0.0], "radius": 0.5, "sigma_a": [0.5, 0.5, 0.5],
            "sigma_s": [1.0, 1.0, 1.0], "amplitude": 0.0, "sharpness": 12.0, **kw}


def with_elements(scene: dict, *elements: dict, resolution: int = 16) -> dict:
    scene = copy.deepcopy(scene)
    scene["medium"]["elements"] = [dict(e) for e in elements]
    scene["medium"]["resolution"] = resolution
    return resolve_scene(scene)


# ----------------------------------------------------------------------------- determinism


def test_spec_is_deterministic_for_a_seed(scene_config):
    a, b = resolve_scene(scene_config()), resolve_scene(scene_config())
    assert a == b and spec_hash(a) == spec_hash(b)
    assert json.loads(json.dumps(a)) == a  # plain JSON, as written to scene.json
    assert len(spec_hash(a)) == 10


def test_different_seeds_give_different_specs(scene_config):
    a = resolve_scene(scene_config("scene.seed=0"))
    b = resolve_scene(scene_config("scene.seed=1"))
    assert a["medium"]["elements"] != b["medium"]["elements"]
    assert spec_hash(a) != spec_hash(b)
    c = resolve_scene(scene_config("scene.cameras.seed=1"))
    assert c["medium"] == a["medium"] and spec_hash(c) != spec_hash(a)


@pytest.mark.parametrize("override", ["scene.spp=33", "scene.cameras.width=31",
                                      "scene.environments.sky_seeds=[3]",
                                      "scene.effects.max_scattering_order=2"])
def test_any_change_changes_the_hash(scene_config, override):
    assert spec_hash(resolve_scene(scene_config(override))) != spec_hash(
        resolve_scene(scene_config()))


# ----------------------------------------------------------------------------- effects rules


def test_isotropic_scene_has_zero_g_and_grey_extinction(scene_config):
    spec = resolve_scene(scene_config("scene=isotropic", "scene.medium.resolution=16"))
    assert spec["effects"] == {"phase": "isotropic", "chromatic": False,
                               "max_scattering_order": -1, "emitters": []}
    for e in spec["medium"]["elements"]:
        assert e["g"] == 0.0
        np.testing.assert_allclose(sigma_t(e), sigma_t(e)[0], rtol=1e-12)
    grids = medium_grids(spec)
    assert not grids["g"].any()
    t = grids["sigma_a"] + grids["sigma_s"]
    np.testing.assert_allclose(t, t[..., :1].repeat(3, -1), rtol=1e-5, atol=1e-6)


def test_isotropic_overrides_explicit_g(scene_config):
    scene = scene_config("scene.effects.phase=isotropic")
    spec = with_elements(scene, blob(g=0.7))
    assert spec["medium"]["elements"][0]["g"] == 0.0


def test_hg_scene_shares_one_g_from_the_range(scene_config):
    spec = resolve_scene(scene_config())
    gs = {e["g"] for e in spec["medium"]["elements"]}
    assert len(spec["medium"]["elements"]) == 3 and len(gs) == 1
    assert -0.5 <= gs.pop() <= 0.5
    fixed = resolve_scene(scene_config("scene.medium.g=0.8", "scene.medium.resolution=16"))
    assert {e["g"] for e in fixed["medium"]["elements"]} == {0.8}
    np.testing.assert_allclose(medium_grids(fixed)["g"], 0.8, rtol=1e-6)


def test_varying_hg_draws_one_g_per_element_in_range(scene_config):
    spec = resolve_scene(scene_config("scene=varying_g", "scene.medium.g_range=[0.2,0.9]"))
    gs = [e["g"] for e in spec["medium"]["elements"]]
    assert len(gs) == 4 and len(set(gs)) == 4
    assert all(0.2 <= g <= 0.9 for g in gs)


def test_chromatic_flag_controls_extinction_colour(scene_config):
    grey = resolve_scene(scene_config("scene.effects.chromatic=false"))
    for e in grey["medium"]["elements"]:
        np.testing.assert_allclose(sigma_t(e), sigma_t(e)[0], rtol=1e-12)
    # grey extinction, coloured albedo: the model Mitsuba renders and nrt's media learn
    assert any(np.ptp(np.asarray(e["sigma_s"]) / sigma_t(e)) > 0.05
               for e in grey["medium"]["elements"])
    colour = resolve_scene(scene_config())
    assert any(np.ptp(sigma_t(e)) > 1e-3 for e in colour["medium"]["elements"])
    for e in colour["medium"]["elements"]:
        assert max(sigma_t(e)) <= 5.0 + 1e-9 and min(e["sigma_a"]) >= 0


def test_grey_scene_rejects_coloured_explicit_elements(scene_config):
    scene = scene_config("scene.effects.chromatic=false")
    with pytest.raises(SceneError, match=r"medium\.elements\[0\].*chromatic"):
        with_elements(scene, blob(sigma_s=[1.0, 2.0, 1.0]))


# ----------------------------------------------------------------------------- bad keys


@pytest.mark.parametrize("overrides,key", [
    (["scene.medium.num_elements=5"], "medium.num_elements"),
    (["scene.medium.num_elements=0"], "medium.num_elements"),
    (["scene.effects.phase=foo"], "effects.phase"),
    (["scene.medium.g_range=[-0.99,0.5]"], "medium.g_range"),
    (["scene.medium.g_range=[-0.5,0.96]"], "medium.g_range"),
    (["scene.medium.g_range=[0.5,-0.5]"], "medium.g_range"),
    (["scene.medium.g=0.99"], "medium.g"),
    (["scene.effects.max_scattering_order=-2"], "effects.max_scattering_order"),
    (["scene.bbox=[[1,1,1],[-1,-1,-1]]"], "bbox"),
    (["scene.medium.resolution=1"], "medium.resolution"),
    (["scene.environments.resolution=[2,4]"], "environments.resolution"),
    (["scene.environments.sky_seeds=[]"], "environments"),
    (["+scene.environments.files.noon=/no/such/map.exr"], "environments.files.noon"),
    (["scene.cameras.num_train=0"], "cameras"),
])
def test_out_of_range_keys_raise_scene_error_naming_the_key(scene_config, overrides, key):
    with pytest.raises(SceneError) as info:
        resolve_scene(scene_config(*overrides))
    assert f"'scene.{key}'" in str(info.value)  # the key as users type it
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("element,phase,key", [
    ({"center": [0, 0, 0], "radius": 0.5, "sigma_a": [1, 1, 1]}, "hg", "medium.elements[0]"),
    (blob(sigma_a=[-1.0, 0.5, 0.5], sigma_s=[2.5, 1.0, 1.0]), "hg", "medium.elements[0]"),
    (blob(g=0.99), "varying_hg", "medium.elements[0].g"),
])
def test_bad_explicit_elements_are_named(scene_config, element, phase, key):
    scene = scene_config(f"scene.effects.phase={phase}")
    with pytest.raises(SceneError) as info:
        with_elements(scene, element)
    assert f"'scene.{key}'" in str(info.value)


@pytest.mark.parametrize("overrides", [["scene.cameras.radius=1.7"],
                                       ["scene.bbox=[[-3,-3,-3],[3,3,3]]"]])
def test_cameras_inside_the_box_are_refused(scene_config, overrides):
    spec = resolve_scene(scene_config(*overrides))
    with pytest.raises(SceneError, match=r"'scene\.cameras\.radius'"):
        camera_rig(spec)


def test_camera_rig_views_the_box_from_the_sphere(scene_config):
    rigs, intr = camera_rig(resolve_scene(scene_config()))
    assert {k: v.shape for k, v in rigs.items()} == {"train": (16, 4, 4), "test": (4, 4, 4)}
    for c2w in rigs.values():
        np.testing.assert_allclose(np.linalg.norm(c2w[:, :3, 3], axis=1), 4.5)
        forward = -c2w[:, :3, 2]
        np.testing.assert_allclose(forward, -c2w[:, :3, 3] / 4.5, atol=1e-12)
    assert intr.camera_angle_x == pytest.approx(np.deg2rad(40.0))


# ----------------------------------------------------------------------------- media grids


@pytest.mark.parametrize("scene", ["default", "isotropic", "varying_g"])
def test_grids_are_bounded_and_g_stays_in_the_elements_range(scene_config, scene):
    spec = resolve_scene(scene_config(f"scene={scene}", "scene.medium.resolution=20"))
    grids = medium_grids(spec)
    elements = spec["medium"]["elements"]
    assert grids["sigma_a"].shape == grids["sigma_s"].shape == (20, 20, 20, 3)
    assert all(a.dtype == np.float32 for a in grids.values())
    assert (grids["sigma_a"] >= 0).all() and (grids["sigma_s"] >= 0).all()
    t = grids["sigma_a"] + grids["sigma_s"]
    # Densities lie in [0, 1]: extinction never exceeds the elements' sum (<= 5 each).
    assert (t <= sum(sigma_t(e) for e in elements) + 1e-4).all()
    assert t.max() <= 5.0 * len(elements) and t.max() > 1.0
    gs = [e["g"] for e in elements]
    assert grids["g"].min() >= min(gs) - 1e-6 and grids["g"].max() <= max(gs) + 1e-6


def outer_layer(a: np.ndarray) -> np.ndarray:
    return np.concatenate([a[0].ravel(), a[-1].ravel(), a[:, 0].ravel(), a[:, -1].ravel(),
                           a[:, :, 0].ravel(), a[:, :, -1].ravel()])


@pytest.mark.parametrize("resolution", [8, 16, 32])
def test_density_vanishes_at_the_box_faces(scene_config, resolution):
    """An element filling the whole box: the renderer interpolates the cell-centred grid
    and clamps at the faces, so the outermost cells must be empty for the medium to fade
    to zero there instead of being cut."""
    spec = with_elements(scene_config(), blob(radius=4.0), resolution=resolution)
    grids = medium_grids(spec)
    for key in ("sigma_a", "sigma_s"):
        assert not outer_layer(grids[key]).any(), key
    c = resolution // 2
    assert (grids["sigma_s"][c, c, c] > 0.5).all()  # dense inside


def test_g_is_the_scattering_weighted_mean_where_elements_overlap(scene_config):
    scene = scene_config("scene.effects.phase=varying_hg")
    a = blob(center=[-0.2, 0.0, 0.0], sigma_s=[1.0, 1.0, 1.0], g=0.8, noise_seed=3)
    b = blob(center=[0.2, 0.0, 0.0], sigma_s=[2.0, 3.0, 4.0], g=-0.4, noise_seed=5)
    both = medium_grids(with_elements(scene, a, b))
    only_a = medium_grids(with_elements(scene, a))
    only_b = medium_grids(with_elements(scene, b))
    # Coefficients add up.
    np.testing.assert_allclose(both["sigma_s"], only_a["sigma_s"] + only_b["sigma_s"],
                               atol=1e-5)
    wa, wb = only_a["sigma_s"].mean(-1), only_b["sigma_s"].mean(-1)
    overlap = (wa > 1e-2) & (wb > 1e-2)
    assert overlap.sum() > 10
    expected = (wa * 0.8 + wb * -0.4) / np.maximum(wa + wb, 1e-30)
    np.testing.assert_allclose(both["g"][overlap], expected[overlap], atol=1e-4)
    # Where one element alone scatters, g is its own; where none does, the plain mean.
    np.testing.assert_allclose(both["g"][(wa > 1e-2) & (wb == 0)], 0.8, atol=2e-4)
    np.testing.assert_allclose(both["g"][(wb > 1e-2) & (wa == 0)], -0.4, atol=2e-4)
    np.testing.assert_allclose(both["g"][(wa == 0) & (wb == 0)], 0.2, atol=1e-5)
