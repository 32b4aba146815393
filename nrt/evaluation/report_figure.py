"""``report.png``: what one evaluation found, in one figure.

Top: a caption line (the run, the scene, the metrics and their noise floor). Then, per
plane the scene has (:func:`nrt.evaluation.media.planes`), the middle slices across z, y
and x of the recovered medium, the truth and the signed error on the plane's shared scale
(:mod:`nrt.evaluation.slices`). Below: held-out views re-rendered under novel illumination
beside their photos and an error map, log-tonemapped and scaled by the photo's maximum as
the image metrics are (docs/conventions.md, "Image comparison"), upscaled by nearest
neighbour to at least :data:`VIEW_PX` pixels. Without ground truth the truth and error
slices are left out and the caption says so.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from nrt.evaluation.evaluate import Evaluation
from nrt.evaluation.images import ERROR_RANGE, display, error_heatmap
from nrt.evaluation.media import (
    PROPERTIES,
    Medium,
    Plane,
    medium_from_grids,
    planes,
    resampled,
    resolution,
)
from nrt.evaluation.slices import (
    BAR,
    ERROR_CMAP,
    FONT,
    GAP,
    LABEL_W,
    UNITS,
    VALUE_CMAP,
    Canvas,
    axis_title,
    cell_px,
    draw_slice,
    extend,
    plane_scale,
    write_png,
)
from nrt.physics.tonemap import log_tonemap

VIEW_PX = 256
"""Least size in pixels of a re-rendered view, its photo and its error map."""
NO_TRUTH = ("no ground truth: the truth and error slices, the property MSEs and the noise "
            "floor are left out")
BARS_W = 2 * (BAR + 62)
COLUMNS = ("recovered", "truth", "error")
"""Names of the slice columns in ``Canvas.panels``: ``<column>/<plane label>/<axis>``."""
CAPTION_CHARS = 150


def upscale(img: np.ndarray, least: int = VIEW_PX) -> tuple[np.ndarray, int]:
    """An image repeated by a whole factor (nearest neighbour) so that its shorter side has
    at least ``least`` pixels; and the factor."""
    k = max(1, math.ceil(least / min(img.shape[:2])))
    return np.repeat(np.repeat(img, k, 0), k, 1), k


def caption(source: str, scene: str, metrics: Mapping[str, float], has_truth: bool) -> str:
    """One line: the run, the scene, the property MSEs x100, and the re-render's PSNR, SSIM
    and LPIPS under novel illumination (else seen) with the noise floor's PSNR."""
    parts = [f"run: {source}", f"scene: {scene}"]
    mse = [f"{p} {metrics[f'mse_{p}_x100']:.4g}" for p in PROPERTIES
           if f"mse_{p}_x100" in metrics]
    if mse:
        parts.append("MSE x100: " + ", ".join(mse))
    group = "novel" if "psnr_novel" in metrics else "seen"
    if f"psnr_{group}" in metrics:
        text = f"{group} illumination: PSNR {metrics[f'psnr_{group}']:.2f} dB"
        if f"psnr_noise_floor_{group}" in metrics:
            text += f" (noise floor {metrics[f'psnr_noise_floor_{group}']:.2f} dB)"
        text += "".join(f", {m.upper()} {metrics[f'{m}_{group}']:.3f}" for m in ("ssim", "lpips")
                        if f"{m}_{group}" in metrics)
        parts.append(text)
    if not has_truth:
        parts.append(NO_TRUTH)
    return " | ".join(parts)


def report_figure(medium: Medium, truth: Medium | None, effects: Mapping | None,
                  views: Sequence[tuple[str, np.ndarray, np.ndarray]], text: str,
                  channels: str = "split") -> Canvas:
    """The figure of one evaluation: ``medium`` (and ``truth``, None when unknown) as slices,
    then ``views`` (name, photo, re-render: linear (H, W, 3) radiance) with error maps,
    under the caption ``text``. The medium is drawn on the truth's cells."""
    reference = truth if truth is not None else medium
    medium = resampled(medium, resolution(reference))
    chosen = [p for p in planes(reference, effects, channels) if p.volume(medium) is not None]
    cells = resolution(reference)
    k = cell_px(cells)
    panel = k * cells
    groups = 3 if truth is not None else 1
    group_w = 3 * panel + 2 * GAP
    lines = textwrap.wrap(text, CAPTION_CHARS) or [""]
    top = 14 * len(lines) + 44
    slices_h = len(chosen) * (panel + 3 * GAP)
    tiles = [(name, *(upscale(x)[0] for x in _view_images(photo, render)))
             for name, photo, render in views]
    view_h = [t[1].shape[0] for t in tiles]
    view_w = max((t[1].shape[1] for t in tiles), default=0)
    width = max(LABEL_W + groups * (group_w + 3 * GAP) + BARS_W,
                LABEL_W + 3 * (view_w + 3 * GAP) + BARS_W)
    height = top + slices_h + sum(h + 30 for h in view_h) + GAP + (20 if tiles else 0)
    canvas = Canvas(width, height)
    for i, line in enumerate(lines):
        canvas.text(GAP, 4 + 14 * i, line, fontsize=FONT + 1)
    heads = ["recovered", "truth", "signed error (recovered - truth)"][:groups]
    for g, head in enumerate(heads):
        x0 = LABEL_W + g * (group_w + 3 * GAP)
        canvas.text(x0 + group_w / 2, top - 30, head, ha="center", fontsize=FONT + 1,
                    weight="bold")
        for a in range(3):
            canvas.text(x0 + a * (panel + GAP) + panel / 2, top - 14, axis_title(a),
                        ha="center", fontsize=FONT - 1)
    for r, plane in enumerate(chosen):
        _slice_row(canvas, top + r * (panel + 3 * GAP), plane, medium, truth, k, panel)
    y = top + slices_h + (20 if tiles else 0)
    if tiles:
        canvas.text(GAP, y - 16, "held-out views: photo | re-render | error map "
                    "(log1p tonemap, scaled by the photo's maximum)", fontsize=FONT + 1,
                    weight="bold")
    for (name, *images), h in zip(tiles, view_h, strict=True):
        for c, (img, head) in enumerate(zip(images, ("photo", "re-render", "error map"),
                                            strict=True)):
            x = LABEL_W + c * (img.shape[1] + 3 * GAP)
            canvas.text(x, y, f"{head}: {name}" if c == 0 else head, fontsize=FONT)
            canvas.panels[f"{head}/{name}"] = canvas.image(x, y + 14, img, frame=False)
        from matplotlib.colors import Normalize

        canvas.colorbar(LABEL_W + 3 * (view_w + 3 * GAP), y + 14, BAR, h,
                        Normalize(0, ERROR_RANGE), "inferno",
                        "|log1p error| / log1p(photo max)", "max")
        y += h + 30
    return canvas


def _view_images(photo: np.ndarray, render: np.ndarray) -> tuple[np.ndarray, ...]:
    """Photo and re-render tonemapped as the metrics see them, and the error heat map."""
    scale = float(log_tonemap(torch.as_tensor(photo)).max())
    return display(photo, scale), display(render, scale), error_heatmap(render, photo)


def _slice_row(canvas: Canvas, y: float, plane: Plane, medium: Medium, truth: Medium | None,
               k: int, panel: int) -> None:
    """One plane: the medium's, the truth's and the error's slices, their two bars."""
    ours = plane.volume(medium)
    true = plane.volume(truth) if truth is not None else None
    scale = plane_scale(plane, [ours], true)
    canvas.text(GAP, y + panel / 2, f"{plane.label}", va="center", fontsize=FONT + 1)
    group_w = 3 * panel + 2 * GAP
    shown = [(ours, False)] + ([(true, False), (ours - true, True)] if true is not None else [])
    for g, ((volume, error), column) in enumerate(zip(shown, COLUMNS, strict=False)):
        for a in range(3):
            x = LABEL_W + g * (group_w + 3 * GAP) + a * (panel + GAP)
            draw_slice(canvas, x, y, volume, a, k, scale.norm(error),
                       ERROR_CMAP if error else VALUE_CMAP, f"{column}/{plane.label}")
    x = LABEL_W + len(shown) * (group_w + 3 * GAP)
    canvas.colorbar(x, y, BAR, panel, scale.norm(), VALUE_CMAP, UNITS[plane.prop],
                    extend([ours, true], scale))
    if true is not None:
        canvas.colorbar(x + BAR + 62, y, BAR, panel, scale.norm(True), ERROR_CMAP, "error")


def write_evaluation_report(path: str | Path, grids: Mapping, truth: Mapping | None,
                            effects: Mapping, result: Evaluation, source: str, scene: str,
                            views: int = 3, channels: str = "split") -> np.ndarray:
    """``report.png`` of an nrt-eval: ``grids`` (property grids) against ``truth`` (the
    dataset's ground truth or None), the first ``views`` re-rendered views under novel
    illumination (else the first ones), the caption from ``result.metrics``. Returns the
    image written."""
    names = (result.novel or list(result.renders))[: max(int(views), 0)]
    shown = [(name.replace("_view", " view "), *result.renders[name]) for name in names]
    true = medium_from_grids(truth) if truth is not None else None
    text = caption(source, scene, result.metrics, true is not None)
    canvas = report_figure(medium_from_grids(grids), true, effects, shown, text, channels)
    return write_png(path, canvas)
