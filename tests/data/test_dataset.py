"""Dataset folders: render -> load round trip, the spec-hash cache, every bad input as a
clear DatasetError naming the file or key, and datasets written by other tools."""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

import nrt.data.render as render
from nrt.data.dataset import load_dataset
from nrt.data.exr import read_exr, write_exr
from nrt.data.media import medium_grids
from nrt.data.sky import sky_map
from nrt.data.spec import resolve_scene, spec_hash
from nrt.errors import DatasetError, SceneError

pytestmark = pytest.mark.integration

SPLIT_SIZES = {"train": 16, "test": 4}
"""Views per split of the tiny scene; every view is rendered under each of its three skies."""
SKIES = ["sky0", "sky1", "sky2"]
# A render of a few pixels: enough to exercise the cache without costing seconds.
SMALL = ("scene.cameras.num_train=2", "scene.cameras.num_test=1", "scene.cameras.width=8",
         "scene.cameras.height=8", "scene.spp=4", "scene.medium.resolution=8")


@pytest.fixture(scope="module")
def splits(tiny_dataset):
    return {split: load_dataset(tiny_dataset, split) for split in SPLIT_SIZES}


def file_times(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*")}


# ----------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("split", list(SPLIT_SIZES))
def test_tiny_dataset_shapes(splits, split):
    ds = splits[split]
    views = SPLIT_SIZES[split]
    n = views * len(SKIES)
    assert len(ds) == n and ds.split == split
    assert ds.images.shape == (n, 32, 32, 3) and ds.images.dtype == torch.float32
    assert ds.c2w.shape == (n, 4, 4) and ds.c2w.dtype == torch.float32
    # frames grouped by sky, the same cameras under each
    assert ds.env_names == SKIES
    assert ds.env_index.tolist() == [i for i in range(len(SKIES)) for _ in range(views)]
    torch.testing.assert_close(ds.c2w[:views], ds.c2w[-views:], rtol=0, atol=0)
    assert [tuple(m.radiance.shape) for m in ds.envmaps] == [(32, 64, 3)] * len(SKIES)
    torch.testing.assert_close(ds.bbox, torch.tensor([[-1.0] * 3, [1.0] * 3]))


def test_intrinsics_match_spec_fov(splits):
    for ds in splits.values():
        intr, cams = ds.intrinsics, ds.spec["cameras"]
        assert (intr.width, intr.height) == (cams["width"], cams["height"]) == (32, 32)
        assert intr.camera_angle_x == pytest.approx(math.radians(cams["fov_x_deg"]), rel=1e-9)
        assert intr.fx == pytest.approx(intr.fy)
        assert (intr.cx, intr.cy) == (16.0, 16.0)


def test_spec_and_folder_name_record_the_resolved_scene(splits, tiny_dataset, scene_config):
    spec = resolve_scene(scene_config())
    assert splits["train"].spec == spec == splits["test"].spec
    assert tiny_dataset.name == f"default-{spec_hash(spec)}"
    info = json.loads((tiny_dataset / "scene.json").read_text())
    assert info["spec_hash"] == spec_hash(spec) and info["renderer"]["images"] == 3 * 20


def test_ground_truth_matches_medium_grids(splits):
    ds = splits["train"]
    gt = ds.ground_truth
    assert gt["sigma_a"].shape == gt["sigma_s"].shape == (32, 32, 32, 3)
    assert gt["g"].shape == (32, 32, 32)
    expected = medium_grids(ds.spec)
    for key, value in expected.items():
        np.testing.assert_array_equal(gt[key].numpy(), value, err_msg=key)
    assert (gt["sigma_a"] >= 0).all() and (gt["sigma_s"] > 0).any()


def test_cameras_look_at_the_box_centre(splits):
    for ds in splits.values():
        centre = ds.bbox.mean(0)
        for i in range(len(ds)):
            o, d, img = ds.rays(i)
            assert o.shape == d.shape == img.shape == (32, 32, 3)
            torch.testing.assert_close(o, ds.c2w[i, :3, 3].expand(32, 32, 3))
            assert torch.linalg.norm(o[0, 0] - centre) == pytest.approx(4.5, rel=1e-5)
            torch.testing.assert_close(d.norm(dim=-1), torch.ones(32, 32))
            # The principal point sits between the four central pixels (centres at +0.5).
            mid = d[15:17, 15:17].reshape(-1, 3).mean(0)
            to_centre = (centre - o[0, 0]) / torch.linalg.norm(centre - o[0, 0])
            assert torch.dot(mid / mid.norm(), to_centre) > 1 - 1e-6
            # OpenGL camera: it looks down its local -Z axis.
            torch.testing.assert_close(-ds.c2w[i, :3, 2], to_centre, atol=1e-5, rtol=0)


def test_test_views_are_held_out(splits):
    train, test = splits["train"].c2w[:, :3, 3], splits["test"].c2w[:, :3, 3]
    assert torch.cdist(test, train).min() > 0.1


def test_images_are_finite_non_negative_and_see_the_medium(splits):
    for ds in splits.values():
        assert torch.isfinite(ds.images).all() and (ds.images >= 0).all()
        assert ds.images.amax() > 0
        # The medium occludes and scatters: images are not all alike.
        assert ds.images.std(dim=(1, 2)).min() > 0


def test_envmap_round_trips_exactly(splits, tiny_dataset):
    ds = splits["train"]
    expected = sky_map(ds.spec["environments"]["sky0"])
    np.testing.assert_array_equal(ds.envmaps[0].radiance.numpy(), expected)
    np.testing.assert_array_equal(read_exr(tiny_dataset / "envmaps" / "sky0.exr"), expected)


# ----------------------------------------------------------------------------- caching


def test_unchanged_spec_is_a_no_op(tiny_dataset, tiny_output_dir, scene_config, monkeypatch):
    def no_render(*args, **kwargs):
        raise AssertionError("the cached dataset was rendered again")

    monkeypatch.setattr(render, "render_dataset", no_render)
    monkeypatch.setattr(render, "select_variant", no_render)
    before = file_times(tiny_dataset)
    folder = render.ensure_dataset(scene_config(), tiny_output_dir / "datasets", progress=False)
    assert folder == tiny_dataset
    assert file_times(tiny_dataset) == before


def test_changed_seed_renders_a_new_folder_and_keeps_the_old(tmp_path, scene_config):
    old = render.ensure_dataset(scene_config(*SMALL), tmp_path, progress=False)
    before = file_times(old)
    new = render.ensure_dataset(scene_config(*SMALL, "scene.seed=1"), tmp_path, progress=False)
    assert new != old and new.parent == old.parent == tmp_path
    assert file_times(old) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([old.name, new.name])
    a, b = load_dataset(old), load_dataset(new)
    assert (a.spec["seed"], b.spec["seed"]) == (0, 1)
    assert not torch.equal(a.ground_truth["sigma_s"], b.ground_truth["sigma_s"])


def test_scene_path_is_used_without_rendering(tmp_path, scene_config, monkeypatch):
    def no_render(*args, **kwargs):
        raise AssertionError("scene.path must not render")

    monkeypatch.setattr(render, "render_dataset", no_render)
    (tmp_path / "mine").mkdir()
    folder = render.ensure_dataset(scene_config(f"scene.path={tmp_path}/mine"), tmp_path / "x")
    assert folder == tmp_path / "mine"
    with pytest.raises(DatasetError, match=r"'scene\.path' = '.*/nowhere' is not a dataset folder"):
        render.ensure_dataset(scene_config(f"scene.path={tmp_path}/nowhere"), tmp_path / "x")


def test_incomplete_cached_folder_is_rendered_again(tmp_path, scene_config):
    scene = scene_config(*SMALL)
    stale = render.dataset_folder(resolve_scene(scene), tmp_path)
    (stale / "images").mkdir(parents=True)  # e.g. a copy that was cut short
    (stale / "transforms_train.json").write_text("{")
    folder = render.ensure_dataset(scene, tmp_path, progress=False)
    assert folder == stale and (folder / "scene.json").is_file()
    assert len(load_dataset(folder, "train")) == 2 * len(SKIES)
    assert [p.name for p in tmp_path.iterdir()] == [stale.name]


def test_failed_render_leaves_no_partial_folder(tmp_path, scene_config):
    with pytest.raises(SceneError, match=r"cameras\.radius"):
        render.ensure_dataset(scene_config(*SMALL, "scene.cameras.radius=1.5"), tmp_path,
                              progress=False)
    assert not tmp_path.exists() or not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- bad input


def edit_json(name: str, change: Callable[[dict], object]) -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        path = root / name
        meta = json.loads(path.read_text())
        change(meta)
        path.write_text(json.dumps(meta))

    return corrupt


def set_frame(k: int, key: str, value) -> Callable[[Path], None]:
    return edit_json("transforms_train.json", lambda m: m["frames"][k].__setitem__(key, value))


def set_key(key: str, value) -> Callable[[Path], None]:
    return edit_json("transforms_train.json", lambda m: m.__setitem__(key, value))


def drop_key(key: str) -> Callable[[Path], None]:
    return edit_json("transforms_train.json", lambda m: m.pop(key))


def delete(rel: str) -> Callable[[Path], None]:
    return lambda root: (root / rel).unlink()


def write_bytes(rel: str, data: bytes) -> Callable[[Path], None]:
    return lambda root: (root / rel).write_bytes(data)


def poke_pixel(rel: str, value: float) -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        img = read_exr(root / rel)
        img[3, 5, 1] = value
        write_exr(root / rel, img)

    return corrupt


def replace_image(rel: str, shape: tuple) -> Callable[[Path], None]:
    return lambda root: write_exr(root / rel, np.ones(shape, np.float32))


def truncate(rel: str) -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        data = (root / rel).read_bytes()
        (root / rel).write_bytes(data[: len(data) // 2])

    return corrupt


def rewrite_ground_truth(**changes) -> Callable[[Path], None]:
    def corrupt(root: Path) -> None:
        path = root / "ground_truth.npz"
        with np.load(path) as data:
            arrays = dict(data)
        for key, value in changes.items():
            if value is None:
                arrays.pop(key)
            else:
                arrays[key] = value
        np.savez(path, **arrays)

    return corrupt


def camera_at(position) -> Callable[[Path], None]:
    m = np.eye(4)
    m[:3, 3] = position
    return set_frame(2, "transform_matrix", m.tolist())


IMG = "images/sky0/train_003.exr"
TR = "transforms_train.json"
GT = "ground_truth.npz"
_ROW = [[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]

BAD_INPUTS = {
    # id: (corruption, substrings the message must contain)
    "missing_transforms": (delete(TR), [TR, "not found"]),
    "invalid_json": (write_bytes(TR, b'{"frames": [}'), [TR, "not valid JSON"]),
    "json_not_an_object": (write_bytes(TR, b"[1, 2]"), [TR, "frames"]),
    "no_frames": (set_key("frames", []), [TR, "'frames'"]),
    "frames_not_a_list": (set_key("frames", {"a": 1}), [TR, "'frames'"]),
    "frame_without_file_path": (edit_json(TR, lambda m: m["frames"][1].pop("file_path")),
                                [TR, "frames[1]", "file_path"]),
    "missing_image": (delete(IMG),
                      [TR, "frames[3].file_path", "train_003.exr", "does not exist"]),
    "garbage_exr": (write_bytes(IMG, b"\x00garbage\xff" * 50), ["train_003.exr", "corrupt"]),
    "empty_exr": (write_bytes(IMG, b""), ["train_003.exr", "corrupt"]),
    "truncated_exr": (truncate(IMG), ["train_003.exr"]),
    "nan_pixel": (poke_pixel(IMG, float("nan")), ["train_003.exr", "NaN"]),
    "inf_pixel": (poke_pixel(IMG, float("inf")), ["train_003.exr", "Inf"]),
    "negative_pixel": (poke_pixel(IMG, -0.5), ["train_003.exr", "negative"]),
    "width_disagrees": (set_key("w", 64), [TR, "'w'", "64x32", "32x32"]),
    "height_disagrees": (set_key("h", 30), [TR, "'h'", "32x30"]),
    "images_differ_in_size": (replace_image("images/sky0/train_005.exr", (16, 16, 3)),
                              ["train_005.exr", "16x16", "32x32"]),
    "camera_inside_box": (camera_at([0.1, 0.2, 0.3]), [TR, "frames[2]", "inside"]),
    "camera_on_box_face": (camera_at([1.0, 0.0, 0.0]), [TR, "frames[2]", "inside"]),
    "unknown_environment": (set_frame(1, "environment", "sky9"),
                            [TR, "frames[1].environment", "sky9", "sky0"]),
    "missing_environments": (drop_key("environments"), [TR, "'environments'"]),
    "empty_environments": (set_key("environments", {}), [TR, "'environments'"]),
    "missing_envmap_file": (delete("envmaps/sky0.exr"), ["sky0.exr", "environments"]),
    "corrupt_envmap": (write_bytes("envmaps/sky0.exr", b"nope"), ["sky0.exr"]),
    "envmap_too_small": (replace_image("envmaps/sky0.exr", (2, 4, 3)), ["sky0.exr", "rows"]),
    "matrix_3x3": (set_frame(0, "transform_matrix", np.eye(3).tolist()),
                   [TR, "frames[0].transform_matrix", "4x4"]),
    "matrix_missing": (edit_json(TR, lambda m: m["frames"][0].pop("transform_matrix")),
                       [TR, "frames[0].transform_matrix"]),
    "matrix_not_numbers": (set_frame(0, "transform_matrix", [["a"] * 4] * 4),
                           [TR, "frames[0].transform_matrix"]),
    "matrix_ragged": (set_frame(0, "transform_matrix", [[1, 0, 0], [0, 1, 0, 0]]),
                      [TR, "frames[0].transform_matrix"]),
    "matrix_nan": (set_frame(0, "transform_matrix", [[float("nan")] * 4] * 4),
                   [TR, "frames[0].transform_matrix", "finite"]),
    "matrix_bad_last_row": (set_frame(0, "transform_matrix", _ROW),
                            [TR, "frames[0].transform_matrix", "[0, 0, 0, 1]"]),
    "bbox_bad_shape": (set_key("medium_bbox", [1, 2, 3]), [TR, "'medium_bbox'"]),
    "bbox_not_numbers": (set_key("medium_bbox", "big"), [TR, "'medium_bbox'"]),
    "no_focal_length": (edit_json(TR, lambda m: [m.pop(k) for k in
                                                  ("fl_x", "fl_y", "camera_angle_x")]),
                        [TR, "camera_angle_x", "fl_x"]),
    "zero_fov": (edit_json(TR, lambda m: [m.pop("fl_x"), m.__setitem__("camera_angle_x", 0)]),
                 [TR, "camera_angle_x"]),
    "fov_not_a_number": (edit_json(TR, lambda m: [m.pop("fl_x"),
                                                  m.__setitem__("camera_angle_x", "wide")]),
                         [TR, "camera_angle_x"]),
    "negative_focal": (set_key("fl_x", -10.0), [TR, "fl_x"]),
    "gt_sigma_a_no_channels": (rewrite_ground_truth(sigma_a=np.zeros((32, 32, 32))),
                               [GT, "sigma_a", "(32, 32, 32, 3)"]),
    "gt_sigma_s_wrong_grid": (rewrite_ground_truth(sigma_s=np.zeros((16, 16, 16, 3))),
                              [GT, "sigma_s"]),
    "gt_g_2d": (rewrite_ground_truth(g=np.zeros((32, 32))), [GT, "(Nz, Ny, Nx)"]),
    "gt_g_4d": (rewrite_ground_truth(g=np.zeros((32, 32, 32, 3)),
                                     sigma_a=np.zeros((32, 32, 32, 3, 3)),
                                     sigma_s=np.zeros((32, 32, 32, 3, 3))), [GT, "'g'"]),
    "gt_missing_g": (rewrite_ground_truth(g=None), [GT, "'g'"]),
    "gt_nan": (rewrite_ground_truth(g=np.full((32, 32, 32), np.nan)), [GT, "'g'", "NaN"]),
    "gt_garbage": (write_bytes(GT, b"not a zip file"), [GT, "not a readable NumPy .npz"]),
    "scene_json_invalid": (write_bytes("scene.json", b"{"), ["scene.json", "not valid JSON"]),
}


@pytest.fixture
def dataset_copy(tiny_dataset, tmp_path) -> Path:
    root = tmp_path / "copy"
    shutil.copytree(tiny_dataset, root)
    return root


def test_missing_folder_is_named(tmp_path):
    with pytest.raises(DatasetError, match="no_such_dataset.*does not exist"):
        load_dataset(tmp_path / "no_such_dataset")


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_raises_dataset_error_naming_the_culprit(dataset_copy, case):
    corrupt, expected = BAD_INPUTS[case]
    corrupt(dataset_copy)
    with pytest.raises(DatasetError) as info:
        load_dataset(dataset_copy, "train")
    message = str(info.value)
    for text in expected:
        assert text in message, f"{text!r} not in: {message}"
    assert "\n" not in message  # one paragraph


def test_a_broken_split_leaves_the_other_loadable(dataset_copy):
    delete("images/sky0/test_001.exr")(dataset_copy)
    assert len(load_dataset(dataset_copy, "train")) == 16 * len(SKIES)
    with pytest.raises(DatasetError, match="test_001.exr"):
        load_dataset(dataset_copy, "test")


# ----------------------------------------------------------------------------- other tools


def test_dataset_from_another_tool_loads(tiny_dataset, tmp_path):
    """NeRF-synthetic style: file_path without extension and with './', only
    camera_angle_x, no w/h, no per-frame environment, no medium_bbox, no ground truth
    and no scene.json."""
    src = json.loads((tiny_dataset / "transforms_train.json").read_text())
    root = tmp_path / "foreign"
    (root / "train").mkdir(parents=True)
    (root / "maps").mkdir()
    shutil.copy(tiny_dataset / "envmaps" / "sky0.exr", root / "maps" / "noon.exr")
    frames = []
    sky0 = [f for f in src["frames"] if f["environment"] == "sky0"]
    for i, frame in enumerate(sky0):
        shutil.copy(tiny_dataset / frame["file_path"], root / "train" / f"r_{i}.exr")
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix":
                       frame["transform_matrix"]})
    meta = {"camera_angle_x": src["camera_angle_x"], "environments": {"noon": "maps/noon.exr"},
            "frames": frames}
    (root / "transforms_train.json").write_text(json.dumps(meta))

    ds = load_dataset(root, "train")
    ref = load_dataset(tiny_dataset, "train").select_environments(["sky0"])
    assert ds.ground_truth is None and ds.spec is None
    assert ds.env_names == ["noon"] and ds.env_index.tolist() == [0] * 16
    assert ds.intrinsics.width == ds.intrinsics.height == 32
    assert ds.intrinsics.fx == pytest.approx(ref.intrinsics.fx)
    assert (ds.intrinsics.cx, ds.intrinsics.cy) == (16.0, 16.0)
    torch.testing.assert_close(ds.images, ref.images, rtol=0, atol=0)
    torch.testing.assert_close(ds.c2w, ref.c2w)
    torch.testing.assert_close(ds.bbox, ref.bbox)
    torch.testing.assert_close(ds.envmaps[0].radiance, ref.envmaps[0].radiance)


def test_training_on_a_sky_the_dataset_lacks_names_the_key_to_set(tiny_dataset):
    """A stage told to train on an environment the dataset does not have stops with the
    keys that choose them and the positions it does have."""
    data = load_dataset(tiny_dataset, "train")
    with pytest.raises(DatasetError, match=r"scene\.environments\.train.*positions 0\.\.2"):
        data.select_environments([0, 3])
