"""The split stage 2's components, each on its own: the light fields per sky
(:mod:`nrt.stages.sky_lights`), the uncollided light's cache (:mod:`nrt.stages.uncollided`),
the optional coupling (:mod:`nrt.stages.coupling`) and the density start
(:mod:`nrt.stages.start`). The stage's tests (test_rte_split_stage.py) run them together."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from torch import nn

from nrt.errors import ConfigError, DatasetError, NrtError
from nrt.losses.context import Illumination
from nrt.modules.fields.sh_light_field import SHGridLightField
from nrt.run_dirs import write_run_info
from nrt.stages import uncollided as uncollided_module
from nrt.stages.coupling import COUPLING, AdjointCoupling, coupling_settings
from nrt.stages.sky_lights import SkyLights
from nrt.stages.start import DensityStart, needs_ea_checkpoint, resolve_ea_checkpoint
from nrt.stages.uncollided import UncollidedCache

pytestmark = pytest.mark.unit

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


class Light(nn.Module):
    """The members of a scattered-light field these components read."""

    degree = 1

    def __init__(self):
        super().__init__()
        self.register_buffer("bbox", torch.zeros(2, 3))
        self.register_buffer("radiance_scale", torch.ones(()))
        self.blends: list[float] = []

    def cache_points(self) -> torch.Tensor:
        return torch.zeros(5, 3)

    def set_uncollided(self, coefficients: torch.Tensor, blend: float) -> None:
        self.blends.append(blend)


def sky(index: int, scale: float = 1.0) -> Illumination:
    return Illumination(index, None, None, None, None, scale)


def test_sky_lights_give_each_environment_its_light_field():
    """One light field per training environment, grown by the factory, each over the box at
    its sky's scale; rays find their light by the dataset's environment index, and a light
    that is none of them (a family member's) is lit by the first sky."""
    first, more = Light(), nn.ModuleList()
    lights = SkyLights(first, more, Light)
    skies = [sky(0, 2.0), sky(2, 5.0)]  # the dataset's environments 0 and 2 train
    lights.attach(skies, BOX)
    assert len(lights.fields) == 2 and lights.fields[0] is first and lights.fields[1] is more[0]
    assert [float(light.radiance_scale) for light in lights.fields] == [2.0, 5.0]
    assert all(torch.equal(light.bbox, BOX) for light in lights.fields)
    assert lights.scenes_of(torch.tensor([2, 0, 2])).tolist() == [1, 0, 1]
    assert lights.of_env(2) is more[0]
    assert lights.illumination_of(more[0]) is skies[1]
    assert lights.illumination_of(Light()) is skies[0]
    lights.grow(2)
    assert len(more) == 1  # grows only to the count asked


def test_the_uncollided_cache_refreshes_on_its_schedule_and_blends_after_the_first(monkeypatch):
    """Due at the first step and every ``uncollided_every`` steps after; the first refresh
    replaces the cache (blend 1), later ones blend with ``uncollided_blend``, unless the
    caller says the caches are new (a family member's first refresh when steps draw some
    members); the points are projected in chunks of ``uncollided_chunk``."""
    chunks: list[int] = []

    def projection(points, *args):
        chunks.append(len(points))
        return torch.zeros(len(points), 3, 4)

    monkeypatch.setattr(uncollided_module, "uncollided_sh", projection)
    monkeypatch.setattr(uncollided_module, "extinction", lambda medium: None)
    monkeypatch.setattr(uncollided_module, "detached", lambda medium: medium)
    cache = UncollidedCache({"uncollided_every": 10, "uncollided_directions": 4,
                             "shadow_steps": 2, "uncollided_chunk": 2,
                             "uncollided_blend": 0.5})
    assert cache.due(3)  # nothing cached yet
    light = Light()
    cache.refresh_all([(None, light)], lambda light: sky(0))
    cache.fresh = True
    cache.refresh_all([(None, light)], lambda light: sky(0))
    cache.refresh_all([(None, light)], lambda light: sky(0), first=True)
    assert light.blends == [1.0, 0.5, 1.0] and chunks == [2, 2, 1] * 3
    assert [step for step in range(25) if cache.due(step)] == [0, 10, 20]


@pytest.mark.parametrize("shared", [False, True])
def test_refresh_all_shares_shadow_rays_only_among_the_skies_of_one_medium(monkeypatch, shared):
    """Two skies' lights in one medium and a third light in another: one by one, three
    projections of one sky each; with ``uncollided_shared``, one projection of both skies
    for the first medium and one of one sky for the other, each light given its own
    sky's coefficients."""
    calls: list[int] = []

    def one(points, sigma_t, bbox, envmap, sampler, lights, *args):
        calls.append(1)
        return torch.full((len(points), 3, 4), float(envmap))

    def several(points, sigma_t, bbox, envmaps, *args):
        calls.append(len(envmaps))
        return [torch.full((len(points), 3, 4), float(e)) for e in envmaps]

    monkeypatch.setattr(uncollided_module, "uncollided_sh", one)
    monkeypatch.setattr(uncollided_module, "uncollided_sh_skies", several)
    monkeypatch.setattr(uncollided_module, "extinction", lambda medium: None)
    monkeypatch.setattr(uncollided_module, "detached", lambda medium: medium)
    values: dict[int, float] = {}

    class Recording(Light):
        def set_uncollided(self, coefficients, blend):
            values[id(self)] = float(coefficients.unique())

    lights = [Recording() for _ in range(3)]
    skies = {id(light): Illumination(k, k + 1, None, None, None, 1.0)
             for k, light in enumerate(lights)}
    cache = UncollidedCache({"uncollided_every": 10, "uncollided_directions": 4,
                             "shadow_steps": 2, "uncollided_shared": shared})
    first, second = object(), object()
    cache.refresh_all([(first, lights[0]), (first, lights[1]), (second, lights[2])],
                      lambda light: skies[id(light)])
    assert sorted(calls) == ([1, 2] if shared else [1, 1, 1])
    assert [values[id(light)] for light in lights] == [1.0, 2.0, 3.0]


def test_a_shared_refresh_refuses_lights_with_different_cache_points(monkeypatch):
    """Shadow rays are shared per cache point: lights of one medium whose cache points
    differ cannot share them, and nothing is projected."""
    monkeypatch.setattr(uncollided_module, "extinction", lambda medium: None)

    class Other(Light):
        def cache_points(self):
            return torch.ones(5, 3)

    cache = UncollidedCache({"uncollided_every": 10, "uncollided_directions": 4,
                             "shadow_steps": 2, "uncollided_shared": True})
    lights = [Light(), Other()]
    with pytest.raises(ValueError, match="same cache points"):
        cache.refresh_shared(None, lights, [sky(0), sky(1)], 1.0)
    assert all(light.blends == [] for light in lights)


def test_coupling_settings_default_and_refuse_unknown_keys():
    assert coupling_settings(None) == COUPLING
    assert coupling_settings({"adjoint": True})["adjoint"] is True
    with pytest.raises(ConfigError, match=r"model\.coupling has unknown keys \['adjiont'\]"):
        coupling_settings({"adjiont": True})


def test_the_adjoint_reads_the_light_through_a_leaf_on_its_own_grid():
    """The adjoint lives on the light's SH grid (another light field is refused); the photos
    read the light through a leaf whose gradient the adjoint takes once."""
    with pytest.raises(ConfigError, match="needs model/light_field=sh_grid"):
        AdjointCoupling(Light(), 0.5)
    light = SHGridLightField(1, 4)
    adjoint = AdjointCoupling(light, 0.5)
    assert adjoint.source.shape == light.coefficients.shape
    assert adjoint.grid.coefficients.shape == light.coefficients.shape
    assert {"grid.coefficients", "source"} <= set(adjoint.state_dict())
    read = adjoint.photo_light(light)
    read.coefficients.sum().backward()
    grad = adjoint.take_gradient()
    assert grad is not None and torch.equal(grad, torch.ones_like(light.coefficients))
    assert adjoint.take_gradient() is None


class Medium:
    def __init__(self):
        self.bbox, self.density = BOX, None

    def set_density(self, density) -> None:
        self.density = density


def test_the_density_start_reads_the_ea_run_or_the_truth():
    """``init=ea`` and ``init=oracle`` bake a density (``none`` does not); the oracle bakes
    the truth's channel-mean extinction, needs ground truth, and blends with an EA run
    only given one; a share outside [0, 1] is refused."""
    assert DensityStart({"source": "ea"}).bakes and not DensityStart({"source": "none"}).bakes
    assert needs_ea_checkpoint({"source": "ea"})
    assert not needs_ea_checkpoint({"source": "oracle"})
    assert needs_ea_checkpoint({"source": "oracle", "truth_share": 0.5})
    with pytest.raises(ConfigError, match="init.ea_ckpt"):
        DensityStart({"source": "oracle", "truth_share": 0.5})
    with pytest.raises(ConfigError, match=r"init\.truth_share=1\.5"):
        DensityStart({"source": "oracle", "truth_share": 1.5})
    oracle, medium = DensityStart({"source": "oracle"}), Medium()
    with pytest.raises(DatasetError, match="ground_truth.npz"):
        oracle.bake(medium, None)
    sigma = torch.full((4, 4, 4, 3), 2.0)
    oracle.bake(medium, {"sigma_a": sigma, "sigma_s": 3 * sigma})
    torch.testing.assert_close(medium.density(torch.zeros(7, 3)), torch.full((7,), 8.0))


def test_the_ea_checkpoint_is_the_given_one_else_the_newest_run(tmp_path: Path):
    """``init.ea_ckpt`` when given (a missing file refused naming the fix), else the EA run
    of the scene with the newest checkpoint (none: refused naming the command)."""
    def resolve(**density):
        return resolve_ea_checkpoint({"source": "ea", **density}, "s", "rte", tmp_path)

    with pytest.raises(NrtError, match="nrt-train stage=ea scene=s"):
        resolve()
    with pytest.raises(NrtError, match="is not a checkpoint file"):
        resolve(ea_ckpt=str(tmp_path / "nope.ckpt"))
    for seconds, run in ((2, "run1"), (1, "run2")):  # run1's checkpoint is the newer
        (tmp_path / "s" / "ea" / run / "checkpoints").mkdir(parents=True)
        ckpt = tmp_path / "s" / "ea" / run / "checkpoints" / "last.ckpt"
        ckpt.write_bytes(b"")
        os.utime(ckpt, (seconds, seconds))
    assert resolve().endswith("run1/checkpoints/last.ckpt")
    given = tmp_path / "s" / "ea" / "run2" / "checkpoints" / "last.ckpt"
    assert resolve(ea_ckpt=str(given)) == str(given.resolve())
    assert resolve_ea_checkpoint({"source": "none"}, "s", "rte", tmp_path) is None


def test_the_newest_ea_run_is_looked_up_among_runs_on_the_same_photos(tmp_path: Path):
    """An EA run trained on another dataset (another preset or photo realisation) is never
    picked silently: the newest run on the stage's own dataset is, and with none on it the
    lookup is refused naming both datasets and the fix."""
    for seconds, run, dataset in ((2, "tiny_run", "s-aaaa"), (1, "cpu_run", "s-bbbb")):
        folder = tmp_path / "s" / "ea" / run
        (folder / "checkpoints").mkdir(parents=True)
        (folder / "checkpoints" / "last.ckpt").write_bytes(b"")
        os.utime(folder / "checkpoints" / "last.ckpt", (seconds, seconds))
        write_run_info(folder, dataset_dir=str(tmp_path / "datasets" / dataset))

    def resolve(dataset):
        return resolve_ea_checkpoint({"source": "ea"}, "s", "rte", tmp_path, None, dataset)

    assert resolve(None).endswith("tiny_run/checkpoints/last.ckpt")  # no dataset: the newest
    assert resolve("s-bbbb").endswith("cpu_run/checkpoints/last.ckpt")
    with pytest.raises(NrtError, match="trained on other photos") as error:
        resolve("s-cccc")
    assert "s-aaaa" in str(error.value) and "init.ea_ckpt=" in str(error.value)
