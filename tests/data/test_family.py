"""``nrt-data scene=family``: K members rendered for real by Mitsuba (a few pixels each),
one shared training sky and a held-back one, the manifest, reuse of the cache, and bad
input refused before rendering."""

from __future__ import annotations

import itertools
import json
import time
from pathlib import Path

import numpy as np
import pytest

from nrt.data.dataset import load_dataset
from nrt.data.exr import read_exr
from nrt.data.family import FAMILY_FILE, load_family, member_scenes, unseen_member_scenes
from nrt.data.render import ensure_dataset
from nrt.errors import DatasetError, SceneError
from tests.cli.test_cli_data import SMALL, assert_refused_before_rendering, file_times, nrt_data
from tests.conftest import compose_config

pytestmark = pytest.mark.e2e

K = 4  # the tiny preset's budget.family.members
MISTAKES = {"family.members": "scene.family.members=0",
            "family.heldout_sky": "scene.family.heldout_sky=null"}


def dataset_times(data_dir: Path) -> dict[str, int]:
    """Modification times of every file of the family and its members (not the logs)."""
    return {k: v for k, v in file_times(data_dir).items() if not k.startswith("logs")}


@pytest.fixture(scope="module")
def family(tmp_path_factory) -> dict:
    """The family rendered once (with the refused invocations started beside it), then the
    same command again: ``first``, ``second`` (CompletedProcess), ``folder``, the file
    times between the two (``times``), and each mistake's ``(CompletedProcess, cwd)``."""
    cwd = tmp_path_factory.mktemp("family")
    args = ("scene=family", "preset=tiny", *SMALL, "render.progress=false")
    start_first = nrt_data(*args, cwd=cwd, wait=False)
    mistakes = {}
    for key, override in MISTAKES.items():
        mistake_cwd = tmp_path_factory.mktemp(f"family_{key.replace('.', '_')}")
        mistakes[key] = (nrt_data("scene=family", "preset=tiny", override, cwd=mistake_cwd,
                                  wait=False), mistake_cwd)
    first = start_first()
    assert first.returncode == 0, first.stderr
    folder = Path(first.stdout.strip())
    times = dataset_times(folder.parent)
    started = time.perf_counter()
    second = nrt_data(*args, cwd=cwd)
    return {"first": first, "second": second, "folder": folder, "times": times,
            "second_s": time.perf_counter() - started,
            **{key: (finish(), c) for key, (finish, c) in mistakes.items()}}


def test_renders_k_members_listed_in_the_manifest(family):
    folder = family["folder"]
    assert folder.name.startswith("family-") and (folder / FAMILY_FILE).is_file()
    assert f"{K} rendered" in family["first"].stderr
    manifest = json.loads((folder / FAMILY_FILE).read_text())
    assert [m["seed"] for m in manifest["members"]] == list(range(K))
    loaded = load_family(folder)
    assert len(loaded) == K and loaded.member(2).seed == 2
    assert loaded.train_environment == "sky0" and loaded.heldout_environment == "sky1"
    for member in loaded.members:
        assert member.folder.parent == folder.parent  # a dataset of the ordinary cache
        assert member.folder.name.startswith(f"family_seed{member.seed}-")
        assert member.environments == {"train": "sky0", "heldout": "sky1"}
        for split in ("train", "test"):  # the existing loader reads a member unchanged
            data = load_dataset(member.folder, split)
            assert data.env_names == ["sky0", "sky1"]
    with pytest.raises(DatasetError, match="no member 4"):
        loaded.member(K)


def test_members_have_distinct_media(family):
    grids = [np.load(f / "ground_truth.npz") for f in load_family(family["folder"]).folders()]
    for a, b in itertools.combinations(grids, 2):
        assert not np.array_equal(a["sigma_s"], b["sigma_s"])


def test_one_shared_training_sky_and_a_different_held_back_one(family):
    folders = load_family(family["folder"]).folders()
    train = [read_exr(f / "envmaps" / "sky0.exr") for f in folders]
    heldout = [read_exr(f / "envmaps" / "sky1.exr") for f in folders]
    for other in train[1:] + heldout[1:]:
        assert other.shape == train[0].shape
    assert all(np.array_equal(t, train[0]) for t in train[1:])
    assert all(np.array_equal(h, heldout[0]) for h in heldout[1:])
    assert not np.allclose(train[0], heldout[0])


def test_second_invocation_reuses_every_member(family):
    second = family["second"]
    assert second.returncode == 0, second.stderr
    assert second.stdout == family["first"].stdout
    assert "0 rendered in" in second.stderr and f"{K} reused" in second.stderr
    assert "Rendered" not in second.stderr and "variant" not in second.stderr  # no Mitsuba
    assert dataset_times(family["folder"].parent) == family["times"]
    assert family["second_s"] < 30, family["second_s"]


@pytest.mark.parametrize("key", list(MISTAKES))
def test_bad_family_is_refused_with_status_2(family, key):
    assert_refused_before_rendering(*family[key], key)


@pytest.mark.parametrize("change, key", [
    ({"members": 2.5}, "family.members"),
    ({"heldout_sky": 0}, "family.heldout_sky"),
    ({"train_sky": None}, "family.train_sky"),
    ({"elements": [{"center": [0, 0, 0], "radius": 0.5, "sigma_a": [1, 1, 1],
                    "sigma_s": [1, 1, 1]}]}, "medium.elements"),
])
def test_family_keys_are_checked(scene_config, change, key):
    scene = scene_config("scene=family")
    if "elements" in change:
        scene["medium"]["elements"] = change["elements"]
    else:
        scene["family"].update(change)
    with pytest.raises(SceneError, match=f"'scene.{key}'"):
        member_scenes(scene)


def test_a_family_is_no_single_dataset(scene_config, tmp_path):
    """``nrt-train scene=family`` and ``nrt-eval`` reach ensure_dataset: refused, naming
    nrt-data, before anything is rendered."""
    with pytest.raises(SceneError, match="nrt-data scene=<family>"):
        ensure_dataset(scene_config("scene=family"), tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_members_follow_the_seed_and_the_two_skies(scene_config):
    members = member_scenes(scene_config("scene=family", "scene.seed=10"))
    assert [m["seed"] for m in members] == [10, 11, 12, 13]
    assert [m["name"] for m in members][0] == "family_seed10"
    assert all(m["environments"]["sky_seeds"] == [0, 1] for m in members)
    assert all("family" not in m for m in members)


def test_unseen_members_are_the_seeds_after_the_members(scene_config):
    """New media of the family come from the seeds after its K members', drawn as members
    are: the members of a family of K + 3 are the family's K, then the 3 unseen."""
    scene = scene_config("scene=family", "scene.seed=10")
    unseen = unseen_member_scenes(scene, 3)
    assert [m["seed"] for m in unseen] == [14, 15, 16]
    assert [m["name"] for m in unseen] == ["family_seed14", "family_seed15", "family_seed16"]
    wider = {**scene, "family": {**scene["family"], "members": K + 3}}
    assert member_scenes(wider) == member_scenes(scene) + unseen
    assert unseen_member_scenes(scene, 0) == []
    assert scene["family"]["members"] == K  # the config itself is unchanged
    # disjoint sets: the second set of 2 starts where the first ends
    assert unseen_member_scenes(scene, 2, start=2) == unseen_member_scenes(scene, 4)[2:]
    assert [m["seed"] for m in unseen_member_scenes(scene, 2, start=2)] == [16, 17]
    with pytest.raises(ValueError, match="start"):
        unseen_member_scenes(scene, 2, start=-1)


def test_cpu_and_paper_presets_set_k():
    for preset, k in (("cpu", 16), ("paper", 50)):
        cfg = compose_config("dataset", [f"preset={preset}", "scene=family"])
        assert cfg.scene.family.members == k

