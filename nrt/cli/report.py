"""``nrt-report``: accuracy-versus-time curves of runs (or of a multirun sweep).

    nrt-report outputs/multirun/<timestamp>            # every run of a sweep
    nrt-report RUN_DIR [RUN_DIR ...] --out DIR         # e.g. rte and dpt side by side

Writes ``accuracy_vs_time.png`` (property MSE x100 and held-out PSNR against training
seconds, one curve per run), ``accuracy_vs_time.csv`` (every point) and ``summary.md``
(final values, nrt-eval's novel-illumination PSNR, share of the accuracy/time frontier).

    nrt-report --slices EA_RUN RTE_RUN DPT_RUN [--labels ...] [--truth FILE] [--out DIR|PNG]

draws instead the media side by side (``slices.png``, the paper's Fig. 4 layout): middle
slices of sigma_a, sigma_s, sigma_t (g when it varies) of each run's export or grid file
(stage 1's ``density_grid.npz`` as a grey extinction), the truth and each one's signed
error on shared colour scales (:func:`nrt.evaluation.slices.compare_sources`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from nrt.errors import NrtError


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="nrt-report", description=__doc__.split("\n")[0])
    parser.add_argument("paths", nargs="+", help="run folders, or folders holding runs")
    parser.add_argument("--out", help="output folder (default: <the one folder given>/report, "
                        "or outputs/reports/<timestamp> for several)")
    parser.add_argument("--slices", action="store_true", help="draw the media's middle "
                        "slices side by side (run folders or .npz grid files) instead")
    parser.add_argument("--truth", help="--slices: the true medium (default: the first "
                        "run's dataset's ground_truth.npz)")
    parser.add_argument("--labels", nargs="+", help="--slices: a label per path")
    parser.add_argument("--channels", choices=("mean", "split"), default="mean",
                        help="--slices: an RGB property's mean, or R, G, B apart")
    parser.add_argument("--title", default="", help="--slices: a line above the figure")
    args = parser.parse_args(argv)
    if args.slices:
        error = slices(args)
        if error:
            sys.exit(error)
        return
    try:
        from nrt.evaluation import report

        runs = [report.read_run(p) for p in report.find_runs(args.paths)]
        report.label_runs(runs)
        if args.out:
            out = Path(args.out)
        elif len(args.paths) == 1:
            out = Path(args.paths[0]) / "report"
        else:
            out = Path("outputs") / "reports" / time.strftime("%Y-%m-%d_%H-%M-%S")
        out.mkdir(parents=True, exist_ok=True)
        shares = report.frontier_share(runs, "val/mse_sigma_t_x100")
        png = report.plot(runs, out / "accuracy_vs_time.png")
        report.write_csv(runs, out / "accuracy_vs_time.csv")
        summary = report.summary_markdown(runs, shares)
        (out / "summary.md").write_text(summary)
    except NrtError as exc:
        sys.exit(f"nrt-report: error: {exc}")
    print(summary)
    if shares:
        best = max(shares, key=shares.get)
        print(f"Best accuracy/time frontier (sigma_t MSE): {best} ({shares[best]:.0%} of it)")
    print(f"Wrote {png}, {out / 'accuracy_vs_time.csv'} and {out / 'summary.md'}")


def slices(args: argparse.Namespace) -> str | None:
    """``--slices``: the media's slices into ``--out`` (a .png, or a folder for
    ``slices.png``; default ``outputs/reports/<timestamp>/slices.png``)."""
    try:
        from nrt.evaluation.slices import compare_sources, write_png

        canvas = compare_sources(args.paths, args.labels, args.truth, args.channels, args.title)
        out = Path(args.out or Path("outputs") / "reports" / time.strftime("%Y-%m-%d_%H-%M-%S"))
        png = out if out.suffix == ".png" else out / "slices.png"
        write_png(png, canvas)
    except NrtError as exc:
        return f"nrt-report: error: {exc}"
    print(f"Wrote {png}")
    return None


if __name__ == "__main__":
    main()
