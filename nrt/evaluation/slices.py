"""Middle slices of media on shared colour scales: the panels of ``report.png`` and the
side-by-side comparison of several media (the layout of the paper's Fig. 4).

Every medium is drawn on the reference's cells (the truth's when known, as the property
MSEs are measured). Per plane (:class:`~nrt.evaluation.media.Plane`) one value scale is
shared by every medium and the truth: 0 to the truth's largest value in the slices shown
(a g field: the truth's range); larger values saturate, marked by the colour bar's arrow.
The signed error (medium - truth) uses a diverging map over the same span, +-(max - min),
so a colour of the error reads against the values' bar. Slices are placed pixel-exact and
upscaled by an integer factor with nearest-neighbour, so each cell is a block of pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nrt.evaluation.media import (
    AXES,
    SLICE_AXES,
    Medium,
    Plane,
    middle_slices,
    planes,
    read_medium,
    read_source,
    resampled,
    resolution,
)

VALUE_CMAP = "viridis"
ERROR_CMAP = "RdBu_r"
SLICE_PX = 128
"""Least size in pixels of a slice panel (a whole number of pixels per cell)."""
DPI = 100
FONT = 8
UNITS = {"sigma_a": "per unit length", "sigma_s": "per unit length",
         "sigma_t": "per unit length", "g": "HG anisotropy"}


@dataclass(frozen=True)
class Scale:
    """A plane's colour scale: values in [vmin, vmax], signed error in +-(vmax - vmin)."""

    vmin: float
    vmax: float

    @property
    def span(self) -> float:
        return self.vmax - self.vmin

    def norm(self, error: bool = False):
        from matplotlib.colors import Normalize

        return Normalize(-self.span, self.span) if error else Normalize(self.vmin, self.vmax)


def plane_scale(plane: Plane, volumes: Sequence[np.ndarray | None],
                truth: np.ndarray | None) -> Scale:
    """The shared scale of ``plane``: from the truth's middle slices when known, else from
    every medium's; extinctions start at 0; never empty."""
    source = [truth] if truth is not None else [v for v in volumes if v is not None]
    shown = np.concatenate([s.ravel() for v in source for s in middle_slices(v)])
    lo, hi = float(shown.min()), float(shown.max())
    if plane.prop != "g":
        lo = min(lo, 0.0)
    if hi - lo < 1e-6:
        pad = max(abs(hi), 1.0) * 0.05
        lo, hi = lo - (pad if plane.prop == "g" else 0.0), hi + pad
    return Scale(lo, hi)


def cell_px(cells: int, least: int = SLICE_PX) -> int:
    """Pixels per cell so that ``cells`` cells take at least ``least`` pixels."""
    return max(1, math.ceil(least / cells))


class Canvas:
    """A matplotlib figure whose axes are placed in whole pixels from its top-left."""

    def __init__(self, width: int, height: int):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.width, self.height = int(width), int(height)
        self.fig = Figure(figsize=(self.width / DPI, self.height / DPI), dpi=DPI,
                          facecolor="white")
        FigureCanvasAgg(self.fig)
        self.panels: dict[str, object] = {}
        """Slice and view axes by name (``<column>/<plane>/<axis>``), for tests and callers."""

    def axes(self, x: float, y: float, w: float, h: float):
        """Axes covering pixels [x, x + w) x [y, y + h), y down from the top; no frame
        ticks."""
        ax = self.fig.add_axes((x / self.width, 1 - (y + h) / self.height,
                                w / self.width, h / self.height))
        ax.set_xticks([])
        ax.set_yticks([])
        return ax

    def text(self, x: float, y: float, s: str, **kw) -> None:
        kw.setdefault("fontsize", FONT)
        kw.setdefault("va", "top")
        self.fig.text(x / self.width, 1 - y / self.height, s, **kw)

    def image(self, x: float, y: float, img: np.ndarray, scale: int = 1, frame: bool = True,
              **kw):
        """An image at ``scale`` pixels per image pixel (nearest neighbour), row 0 at the
        top unless ``origin="lower"``; without ``frame`` every pixel is the image's."""
        h, w = img.shape[:2]
        ax = self.axes(x, y, w * scale, h * scale)
        ax.imshow(img, interpolation="nearest", aspect="auto", **kw)
        if not frame:
            ax.set_axis_off()
        return ax

    def colorbar(self, x: float, y: float, w: float, h: float, norm, cmap: str, label: str,
                 extend: str = "neither") -> None:
        from matplotlib.cm import ScalarMappable

        ax = self.fig.add_axes((x / self.width, 1 - (y + h) / self.height,
                                w / self.width, h / self.height))
        bar = self.fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), cax=ax, extend=extend,
                                orientation="vertical" if h > w else "horizontal")
        bar.ax.tick_params(labelsize=FONT - 1)
        bar.set_label(label, fontsize=FONT - 1)


def draw_slice(canvas: Canvas, x: float, y: float, volume: np.ndarray, axis: int,
               scale: int, norm, cmap: str, name: str):
    """The middle slice of ``volume`` across :data:`AXES` [axis], ``scale`` pixels per cell,
    world's up at the top, kept as ``canvas.panels[f"{name}/{AXES[axis]}"]``."""
    ax = canvas.image(x, y, middle_slices(volume)[axis], scale, origin="lower", cmap=cmap,
                      norm=norm)
    canvas.panels[f"{name}/{AXES[axis]}"] = ax
    return ax


def extend(volumes: Sequence[np.ndarray | None], scale: Scale) -> str:
    """The colour bar's arrows: where some drawn value lies outside the scale."""
    shown = [s for v in volumes if v is not None for s in middle_slices(v)]
    low = any(float(s.min()) < scale.vmin - 1e-6 for s in shown)
    high = any(float(s.max()) > scale.vmax + 1e-6 for s in shown)
    return {(False, False): "neither", (True, False): "min", (False, True): "max"}.get(
        (low, high), "both")


def axis_title(axis: int) -> str:
    """``z mid (x -> , y ^)``: the slice's normal and its horizontal and vertical axes."""
    name = AXES[axis]
    right, up = SLICE_AXES[name]
    return f"{name} mid ({right}\u2192, {up}\u2191)"


GAP, LABEL_W, BAR = 6, 96, 12


def comparison_figure(media: Sequence[tuple[str, Medium]], truth: Medium | None,
                      chosen: Sequence[Plane], title: str = "") -> Canvas:
    """Several media side by side (the paper's Fig. 4): a row per medium, the truth first,
    each medium's signed error in the row below it; per plane a group of three columns,
    the middle slices across z, y and x; beneath each group its value and error bars.
    All media must share the reference's cells (:func:`nrt.evaluation.media.resampled`);
    a property a medium lacks (stage 1 learns only sigma_t) is left blank."""
    rows: list[tuple[str, Medium | None, bool]] = []
    if truth is not None:
        rows.append(("truth", truth, False))
    for label, medium in media:
        rows.append((label, medium, False))
        if truth is not None:
            rows.append((f"{label}\nerror", medium, True))
    cells = next(iter((truth or media[0][1]).values())).shape[0]
    k = cell_px(cells)
    panel = k * cells
    group_w = 3 * panel + 2 * GAP
    top = 30 + (22 if title else 0)
    bars_h = 2 * (BAR + 34) if truth is not None else BAR + 34
    width = LABEL_W + len(chosen) * (group_w + 3 * GAP) + GAP
    height = top + len(rows) * (panel + GAP) + bars_h + GAP
    canvas = Canvas(width, height)
    if title:
        canvas.text(GAP, 4, title, fontsize=FONT + 1)
    for g, plane in enumerate(chosen):
        x0 = LABEL_W + g * (group_w + 3 * GAP)
        truth_v = plane.volume(truth) if truth is not None else None
        volumes = [plane.volume(m) for _, m in media]
        scale = plane_scale(plane, volumes, truth_v)
        canvas.text(x0 + group_w / 2, top - 26, plane.label, ha="center", fontsize=FONT + 1,
                    weight="bold")
        for a in range(3):
            canvas.text(x0 + a * (panel + GAP) + panel / 2, top - 12, axis_title(a),
                        ha="center", fontsize=FONT - 1)
        for r, (label, medium, error) in enumerate(rows):
            volume = plane.volume(medium)
            y = top + r * (panel + GAP)
            if volume is None:
                canvas.text(x0 + group_w / 2, y + panel / 2, f"no {plane.prop}", ha="center",
                            va="center", color="grey")
                continue
            for a in range(3):
                x = x0 + a * (panel + GAP)
                name = f"{label}/{plane.label}"
                if error:
                    draw_slice(canvas, x, y, volume - truth_v, a, k, scale.norm(True),
                               ERROR_CMAP, name.replace("\n", " "))
                else:
                    draw_slice(canvas, x, y, volume, a, k, scale.norm(), VALUE_CMAP, name)
        y = top + len(rows) * (panel + GAP) + 4
        canvas.colorbar(x0, y, group_w, BAR, scale.norm(), VALUE_CMAP,
                        f"{plane.label} ({UNITS[plane.prop]})",
                        extend([truth_v, *volumes], scale))
        if truth is not None:
            canvas.colorbar(x0, y + BAR + 34, group_w, BAR, scale.norm(True), ERROR_CMAP,
                            f"{plane.label}: medium - truth")
    for r, (label, _, _) in enumerate(rows):
        canvas.text(GAP, top + r * (panel + GAP) + panel / 2, label, va="center",
                    fontsize=FONT + 1)
    return canvas


def figure_array(canvas: Canvas) -> np.ndarray:
    """The drawn figure as an (H, W, 3) image in [0, 1]."""
    canvas.fig.canvas.draw()
    return np.asarray(canvas.fig.canvas.buffer_rgba())[..., :3].astype(np.float32) / 255


def write_png(path: str | Path, canvas: Canvas) -> np.ndarray:
    """Draw ``canvas`` into ``path`` (8-bit PNG); returns the image written, (H, W, 3) in
    [0, 1] (what TensorBoard is given)."""
    from nrt.evaluation.images import save_png

    image = figure_array(canvas)
    save_png(path, image)
    return image


def compare_sources(paths: Sequence[str | Path], labels: Sequence[str] | None = None,
                    truth: str | Path | None = None, channels: str = "mean",
                    title: str = "") -> Canvas:
    """:func:`comparison_figure` of run folders or grid files (any stage's export). The
    truth is ``truth``, else the first run's dataset's ``ground_truth.npz``, else none; the
    planes follow the first run's scene effects (a bare grid file's: what the grids hold);
    every medium is resampled onto the reference's cells."""
    from nrt.errors import NrtError

    sources = [read_source(p) for p in paths]
    if labels and len(labels) != len(sources):
        raise NrtError(f"--labels gives {len(labels)} labels for {len(sources)} media; give "
                       "one per path, in order.")
    truth_path = truth or next((s.truth for s in sources if s.truth is not None), None)
    true = read_medium(truth_path) if truth_path is not None else None
    effects = next((s.effects for s in sources if s.effects is not None), None)
    reference = true if true is not None else sources[0].medium
    cells = resolution(reference)
    media = [(label, resampled(s.medium, cells))
             for label, s in zip(labels or [s.label for s in sources], sources, strict=True)]
    return comparison_figure(media, true, planes(reference, effects, channels), title)
