"""The README's slices figure of the quickstart: its EA start, stage 2 and the tuned baseline
beside the truth, drawn by ``nrt-report --slices`` from small grids committed to the docs.

    python -m benchmarks.quickstart_slices pack --ea EA_RUN --rte RTE_RUN --dpt DPT_RUN
    python -m benchmarks.quickstart_slices redraw

``pack`` writes the four media into ``docs/data/quickstart_slices/`` in their own formats
(``ground_truth.npz`` of the runs' dataset, stage 1's ``density_grid.npz``, the two
``medium_grids.npz`` as ``stage2.npz`` and ``baseline.npz``), resampled to ``--cells``^3
(default 32: the cells stage 2 and the baseline learn on), as float16 with extinctions
below 0.01 per unit length set to 0, so that they weigh a few hundred KB. ``redraw`` draws
``docs/figures/quickstart_slices_cpu.png`` from them in seconds.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from nrt.data.dataset import GROUND_TRUTH_FILE
from nrt.evaluation.media import read_medium, resampled
from nrt.run_dirs import RUN_FILE

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "docs" / "data" / "quickstart_slices"
FIGURE = ROOT / "docs" / "figures" / "quickstart_slices_cpu.png"
FILES = {"density_grid.npz": "EA start", "stage2.npz": "stage 2", "baseline.npz": "baseline"}
TITLE = ("default scene, cpu preset: the quickstart's EA run, then stage 2 and the tuned "
         "baseline from it for 600 training seconds each; grids resampled to 32^3")
ZERO_BELOW = 0.01
"""Extinctions under this (per unit length) are stored as 0: empty space compresses."""


def small(medium: dict, cells: int) -> dict[str, np.ndarray]:
    """``medium`` on ``cells``^3 cells as float16, near-empty cells zeroed (bbox [-1, 1]^3
    as every preset's box)."""
    out = {}
    for key, value in resampled(medium, cells).items():
        if key == "sigma_t" and "sigma_a" in medium:
            continue
        if key != "g":
            value = np.where(value < ZERO_BELOW, 0.0, value)
        out["density" if key == "sigma_t" else key] = value.astype(np.float16)
    out["bbox"] = np.array([[-1, -1, -1], [1, 1, 1]], np.float32)
    return out


def pack(ea: Path, rte: Path, dpt: Path, cells: int) -> None:
    dataset = Path(json.loads((rte / RUN_FILE).read_text())["dataset_dir"])
    sources = {"ground_truth.npz": dataset / GROUND_TRUTH_FILE, "density_grid.npz": ea,
               "stage2.npz": rte, "baseline.npz": dpt}
    DATA.mkdir(parents=True, exist_ok=True)
    for name, source in sources.items():
        np.savez_compressed(DATA / name, **small(read_medium(source), cells))
        print(f"{DATA / name}: {(DATA / name).stat().st_size / 1024:.0f} KB from {source}")


def redraw() -> None:
    from nrt.cli.report import main as nrt_report

    nrt_report(["--slices", *(str(DATA / f) for f in FILES), "--truth",
                str(DATA / "ground_truth.npz"), "--labels", *FILES.values(),
                "--title", TITLE, "--out", str(FIGURE)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack", help="write the small grids from the run folders")
    p.add_argument("--ea", type=Path, required=True, help="the quickstart's EA run folder")
    p.add_argument("--rte", type=Path, required=True, help="stage 2's run folder")
    p.add_argument("--dpt", type=Path, required=True, help="the baseline's run folder")
    p.add_argument("--cells", type=int, default=32)
    sub.add_parser("redraw", help="draw the figure from the committed grids")
    args = parser.parse_args()
    if args.command == "pack":
        pack(args.ea, args.rte, args.dpt, args.cells)
    else:
        redraw()


if __name__ == "__main__":
    main()
