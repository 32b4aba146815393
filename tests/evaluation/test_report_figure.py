"""The report figures show what the grids hold: a known blob lands on the expected pixels of
each middle slice, a medium against itself has a zero error panel, the colour scale is one
for the medium and the truth, the views are upscaled by whole factors, and every stage's
export (stage 1's density, stage 2's and the baseline's grids, a dataset's ground truth)
draws, through ``nrt-report --slices`` too."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch
from matplotlib import colormaps
from PIL import Image

from nrt.cli.report import main as nrt_report
from nrt.data.grids import save_property_grids
from nrt.evaluation.images import display, error_heatmap
from nrt.evaluation.media import Plane, middle_slices, planes, read_medium
from nrt.evaluation.report_figure import NO_TRUTH, VIEW_PX, caption, report_figure, upscale
from nrt.evaluation.slices import compare_sources, comparison_figure, write_png
from nrt.physics.tonemap import log_tonemap

pytestmark = pytest.mark.unit

N = 16
BLOBS = {"z": ((8, 3, 12), (3, 12)),   # cell (z, y, x) -> (row, column) in its slice image
         "y": ((2, 8, 5), (2, 5)),     # slice across y: rows z, columns x
         "x": ((13, 10, 8), (10, 13))}  # slice across x: rows y, columns z
"""One bright cell in each middle slice (z, y, x = 8), and where each slice shows it."""
EFFECTS = {"phase": "hg", "chromatic": True}


def blob_medium(value: float = 2.0) -> dict[str, np.ndarray]:
    """A grey medium, 0 everywhere but the cells of :data:`BLOBS` (sigma_s = value)."""
    sigma_s = np.zeros((N, N, N, 3), np.float32)
    for cell, _ in BLOBS.values():
        sigma_s[cell] = value
    sigma_a = 0.1 * sigma_s
    return {"sigma_a": sigma_a, "sigma_s": sigma_s, "sigma_t": sigma_a + sigma_s,
            "g": np.full((N, N, N), 0.3, np.float32)}


def pixel_colours(image: np.ndarray, ax, cells: int) -> np.ndarray:
    """The PNG's colour at the centre of each cell of a slice panel, (rows, cols, 3), row 0
    the lowest coordinate (as the slice array)."""
    box = ax.get_window_extent()
    height = image.shape[0]
    k = box.width / cells
    cols = (box.x0 + (np.arange(cells) + 0.5) * k).astype(int)
    rows = (height - box.y0 - (np.arange(cells) + 0.5) * k).astype(int)  # from the bottom up
    return image[rows[:, None], cols[None, :]]


def test_a_blob_shows_at_its_cell_in_each_middle_slice(tmp_path):
    medium = blob_medium()
    canvas = report_figure(medium, None, EFFECTS, [], "blob")
    written = write_png(tmp_path / "report.png", canvas)
    png = np.asarray(Image.open(tmp_path / "report.png").convert("RGB")) / 255.0
    np.testing.assert_allclose(png, written, atol=1 / 255)
    top = np.asarray(colormaps["viridis"](1.0)[:3])
    bottom = np.asarray(colormaps["viridis"](0.0)[:3])
    for axis, (_, (row, col)) in BLOBS.items():
        colours = pixel_colours(png, canvas.panels[f"recovered/sigma_s/{axis}"], N)
        bright = np.linalg.norm(colours - top, axis=-1) < 0.02
        dark = np.linalg.norm(colours - bottom, axis=-1) < 0.02
        expected = np.zeros((N, N), bool)
        expected[row, col] = True
        np.testing.assert_array_equal(bright, expected, err_msg=f"slice across {axis}")
        assert dark.sum() == N * N - 1, axis


def test_middle_slices_are_oriented_with_the_world_axes():
    volume = np.zeros((N, N, N), np.float32)
    for cell, _ in BLOBS.values():
        volume[cell] = 1.0
    for image, (axis, (_, (row, col))) in zip(middle_slices(volume), BLOBS.items(), strict=True):
        assert image.shape == (N, N)
        assert image[row, col] == 1.0 and image.sum() == 1.0, axis


def test_a_medium_against_itself_has_a_zero_error_panel(tmp_path):
    medium = blob_medium()
    canvas = report_figure(medium, medium, EFFECTS, [], "itself")
    png = write_png(tmp_path / "report.png", canvas)
    zero = np.asarray(colormaps["RdBu_r"](0.5)[:3])
    errors = [k for k in canvas.panels if k.startswith("error/")]
    # sigma_a, sigma_s and sigma_t are grey here (one row each), g is one value (not drawn)
    assert {k.split("/")[1] for k in errors} == {"sigma_a", "sigma_s", "sigma_t"}
    for key in errors:
        assert not np.any(canvas.panels[key].images[0].get_array())
        colours = pixel_colours(png, canvas.panels[key], N)
        assert np.abs(colours - zero).max() < 0.02, key
    # a medium twice as dense: its error (+2, the scale's span) at the blob, the top red
    canvas = report_figure(blob_medium(4.0), medium, EFFECTS, [], "twice")
    png = write_png(tmp_path / "twice.png", canvas)
    colours = pixel_colours(png, canvas.panels["error/sigma_s/z"], N)
    row, col = BLOBS["z"][1]
    assert np.abs(colours[row, col] - colormaps["RdBu_r"](1.0)[:3]).max() < 0.02
    assert np.abs(colours[0, 0] - zero).max() < 0.02


def test_the_colour_scale_is_shared_by_medium_and_truth(tmp_path):
    truth = blob_medium(2.0)
    canvas = report_figure(blob_medium(1.0), truth, EFFECTS, [], "half")
    png = write_png(tmp_path / "report.png", canvas)
    ours, true, error = (canvas.panels[f"{c}/sigma_s/z"].images[0] for c in
                         ("recovered", "truth", "error"))
    assert (ours.norm.vmin, ours.norm.vmax) == (true.norm.vmin, true.norm.vmax) == (0.0, 2.0)
    assert (error.norm.vmin, error.norm.vmax) == (-2.0, 2.0)
    row, col = BLOBS["z"][1]
    half = np.asarray(colormaps["viridis"](0.5)[:3])
    for column, expected in (("recovered", half), ("truth", colormaps["viridis"](1.0)[:3])):
        colours = pixel_colours(png, canvas.panels[f"{column}/sigma_s/z"], N)
        assert np.abs(colours[row, col] - expected).max() < 0.02, column
    # the comparison figure: one scale per plane across every medium's row
    figure = comparison_figure([("half", blob_medium(1.0)), ("double", blob_medium(4.0))],
                               truth, planes(truth, EFFECTS, "mean"))
    norms = {(a.images[0].norm.vmin, a.images[0].norm.vmax) for k, a in figure.panels.items()
             if k.split("/")[1] == "sigma_s" and "error" not in k}
    assert norms == {(0.0, 2.0)}
    errors = {(a.images[0].norm.vmin, a.images[0].norm.vmax) for k, a in figure.panels.items()
              if k.split("/")[1] == "sigma_s" and "error" in k}
    assert errors == {(-2.0, 2.0)}


def test_planes_follow_the_effects_and_the_channels():
    rgb = blob_medium()
    rgb["sigma_a"] = rgb["sigma_a"] * np.array([1.0, 2.0, 3.0], np.float32)
    rgb["sigma_t"] = rgb["sigma_a"] + rgb["sigma_s"]
    labels = [p.label for p in planes(rgb, EFFECTS)]
    assert labels == ["sigma_a R", "sigma_a G", "sigma_a B", "sigma_s",
                      "sigma_t R", "sigma_t G", "sigma_t B"]
    assert [p.label for p in planes(rgb, EFFECTS, "mean")] == [
        "sigma_a, RGB mean", "sigma_s", "sigma_t, RGB mean"]
    varying = {**rgb, "g": np.linspace(-0.5, 0.5, N ** 3, dtype=np.float32).reshape((N,) * 3)}
    assert planes(varying, {**EFFECTS, "phase": "varying_hg"})[-1] == Plane("g")
    assert planes(varying, None)[-1] == Plane("g")  # no effects: drawn because it varies
    assert Plane("g") not in planes(varying, {**EFFECTS, "phase": "isotropic"})
    grey = {"sigma_t": rgb["sigma_s"][..., 0]}  # stage 1: a grey extinction only
    assert [p.label for p in planes(grey, EFFECTS)] == ["sigma_t"]
    assert Plane("sigma_t", 1).volume(grey) is grey["sigma_t"]
    assert Plane("sigma_a", 0).volume(grey) is None


def test_views_are_tonemapped_as_the_metrics_and_upscaled_by_whole_factors(tmp_path):
    rng = np.random.default_rng(0)
    photo = rng.uniform(0, 3, (32, 40, 3)).astype(np.float32)
    render = photo * 1.2
    canvas = report_figure(blob_medium(), None, EFFECTS, [("sky2 view 004", photo, render)],
                           "views")
    png = write_png(tmp_path / "report.png", canvas)
    scale = float(log_tonemap(torch.as_tensor(photo)).max())
    expected = {"photo": display(photo, scale), "re-render": display(render, scale),
                "error map": error_heatmap(render, photo)}
    for head, image in expected.items():
        ax = canvas.panels[f"{head}/sky2 view 004"]
        box = ax.get_window_extent()
        assert min(box.height, box.width) > VIEW_PX - 0.5, head
        big, k = upscale(image)
        assert k == 8 and big.shape == (256, 320, 3)
        y0 = png.shape[0] - int(round(box.y1))
        x0 = int(round(box.x0))
        shown = png[y0:y0 + big.shape[0], x0:x0 + big.shape[1]]
        np.testing.assert_allclose(shown, big, atol=1.5 / 255, err_msg=head)


def test_caption_names_the_run_the_metrics_and_their_noise_floor():
    metrics = {"mse_sigma_t_x100": 5.68, "mse_g_x100": 0.005, "psnr_novel": 36.38,
               "psnr_noise_floor_novel": 37.11, "ssim_novel": 0.98, "lpips_novel": 0.015,
               "psnr_seen": 38.0}
    text = caption("outputs/default/rte/x", "default", metrics, True)
    for needle in ("run: outputs/default/rte/x", "scene: default", "sigma_t 5.68", "g 0.005",
                   "novel illumination: PSNR 36.38 dB (noise floor 37.11 dB)", "SSIM 0.980",
                   "LPIPS 0.015"):
        assert needle in text
    assert NO_TRUTH not in text
    bare = caption("grids.npz", "default", {"psnr_novel": 30.0}, False)
    assert NO_TRUTH in bare and "MSE x100" not in bare and "(noise floor" not in bare


def test_without_truth_only_the_recovered_slices_are_drawn():
    canvas = report_figure(blob_medium(), None, EFFECTS, [], "no truth")
    columns = {k.split("/")[0] for k in canvas.panels}
    assert columns == {"recovered"}


@pytest.fixture
def exports(tmp_path):
    """Every stage's export of one blob medium: a dataset's ground truth (16^3), stage 1's
    density (8^3, grey), stage 2's and the baseline's grids (16^3 and 8^3)."""
    truth = blob_medium()
    bbox = np.array([[-1, -1, -1], [1, 1, 1]], np.float32)
    save_property_grids(tmp_path / "ground_truth.npz", truth, bbox)
    coarse = truth["sigma_t"][::2, ::2, ::2, 0]
    np.savez_compressed(tmp_path / "density_grid.npz", density=coarse, bbox=bbox)
    save_property_grids(tmp_path / "medium_grids.npz", blob_medium(1.5), bbox)
    small = {k: v[::2, ::2, ::2] for k, v in blob_medium(2.5).items()}
    save_property_grids(tmp_path / "baseline.npz", small, bbox)
    return tmp_path


def test_every_stage_export_reads_and_draws_side_by_side(exports, tmp_path):
    assert set(read_medium(exports / "density_grid.npz")) == {"sigma_t"}
    assert set(read_medium(exports / "medium_grids.npz")) == {"sigma_a", "sigma_s",
                                                              "sigma_t", "g"}
    start = time.perf_counter()
    out = tmp_path / "out" / "slices.png"
    nrt_report(["--slices", str(exports / "density_grid.npz"), str(exports / "medium_grids.npz"),
                str(exports / "baseline.npz"), "--truth", str(exports / "ground_truth.npz"),
                "--labels", "EA start", "stage 2", "baseline", "--out", str(out)])
    assert time.perf_counter() - start < 10
    assert out.is_file() and Image.open(out).size[0] > 1000
    canvas = compare_sources([exports / "density_grid.npz", exports / "baseline.npz"],
                             ["EA", "baseline"], exports / "ground_truth.npz")
    rows = {k.split("/")[0] for k in canvas.panels}
    assert rows == {"truth", "EA", "EA error", "baseline", "baseline error"}
    # stage 1 draws sigma_t only; the 8^3 grids are drawn on the truth's 16^3 cells
    assert {k.split("/")[1] for k in canvas.panels if k.startswith("EA/")} == {"sigma_t"}
    assert canvas.panels["baseline/sigma_s/z"].images[0].get_array().shape == (N, N)


def test_report_slices_errors_are_one_line(exports, capsys):
    with pytest.raises(SystemExit) as exc:
        nrt_report(["--slices", str(exports / "missing.npz")])
    assert "nrt-report: error:" in str(exc.value) and "missing.npz" in str(exc.value)
    with pytest.raises(SystemExit) as exc:
        nrt_report(["--slices", str(exports / "medium_grids.npz"), "--labels", "a", "b"])
    assert "--labels gives 2 labels for 1 media" in str(exc.value)
