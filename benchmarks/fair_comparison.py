"""Stage 2 against the path-tracing baseline on equal terms, with its data kept in the repository.

``run``: for each scene and photo-noise realisation (``scene.photo_seed``; realisation N > 0
is the scene named ``<scene>_photo<N>``), the EA checkpoint (the newest under
``outputs/``, else a new stage-1 run on those photos), then each method from that one
checkpoint for ``--budget-s`` training seconds: ``rte`` (stage 2), ``dpt`` (the baseline
at its defaults) and, on the ``--paper-on`` scenes, ``rte_paper`` (the paper's
formulation). Both stage 2 and the baseline start from the EA density baked on the same
cells and learn g. The property MSE is measured every ``--every-s`` training seconds with
the clock paused (for every method alike), and ``nrt-eval`` re-renders each result with
Mitsuba under the held-back sky at the dataset's spp, beside the true medium's noise
floor: one measurement for all methods. With ``--photo-variant scalar_rgb`` new photos are
rendered by Mitsuba's scalar fallback (the variant where LLVM is missing) as realisations
of their own (``<scene>_photo<N>_scalar_rgb``, folder ``photo<N>_scalar_rgb``). Per run,
``<data>/<scene>/photo<N>/<method>.csv``
(the curves) and ``<method>.json`` (nrt-eval's metrics, steps, seconds) are written; a
run whose JSON exists is skipped, so a killed comparison resumes. ``--given-to-all`` adds
training overrides to every method alike (``budget.rte.medium_resolutions=[4,8,16,32,64]``
moves both methods' grid schedule: the baseline's follows stage 2's); they are recorded, and
one data folder holds one set of them.

``redraw``: the figure (property MSE against training seconds, every scene and
realisation, log time) and the Markdown table (mean and spread over realisations per scene
and method; stage 2 against the baseline over the blind scenes and over all, as per-scene
ratios; time-to-accuracy; each realisation's commits, whether its methods started from the
same EA weights and the machine's speed before each) from those files alone.

    python -m benchmarks.fair_comparison run [--scenes default,heldout,...] [--photo-seeds 0,1]
        [--photo-variant auto] [--methods rte,dpt,rte_paper] [--paper-on default]
        [--given-to-all KEY=VALUE ...]
        [--budget-s 600] [--every-s 25] [--preset cpu] [--data DIR] [--out DIR]
    python -m benchmarks.fair_comparison redraw [--data DIR] [--figure PNG] [--table MD]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import (
    BLIND_SCENES,
    SCENES,
    add_budget_arguments,
    commit_of,
    ea_checkpoint,
    output_dir,
)
from benchmarks.equal_time import (
    EVAL_KEYS,
    PROPERTIES,
    read_record,
    run_method,
    summary_line,
)

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "docs" / "data" / "fair_comparison"
FIGURE = ROOT / "docs" / "figures" / "fair_comparison_cpu.png"
METHODS = {"rte": ["stage=rte"], "dpt": ["stage=dpt"],
           "rte_paper": ["stage=rte", "experiment=rte_paper"]}
LABELS = {"rte": "stage 2 (nrt)", "dpt": "path tracing (baseline)",
          "rte_paper": "paper's formulation"}
COLOURS = {"rte": "tab:blue", "dpt": "tab:red", "rte_paper": "tab:green"}


def scene_overrides(scene: str, photo_seed: int, variant: str = "auto"
                    ) -> tuple[str, list[str]]:
    """The name of a realisation and its overrides of the default scene; photos rendered by
    Mitsuba's ``variant`` (``auto``: the best one present) when they are rendered."""
    if photo_seed == 0 and variant == "auto":
        return scene, list(SCENES[scene])
    name = f"{scene}_photo{photo_seed}" + ("" if variant == "auto" else f"_{variant}")
    return name, [*SCENES[scene], f"scene.photo_seed={photo_seed}", f"scene.name={name}",
                  *([] if variant == "auto" else [f"render.variant={variant}"])]


def realisation_folder(photo_seed: int, variant: str = "auto") -> str:
    """``photo<N>``, or ``photo<N>_<variant>`` for photos rendered by a chosen variant."""
    return f"photo{photo_seed}" + ("" if variant == "auto" else f"_{variant}")


def run_all(args) -> None:
    methods = args.methods.split(",")
    code = commit_of(ROOT)  # the commit whose configs hold each method's defaults
    realisations = [(scene, seed) for scene in args.scenes.split(",")
                    for seed in map(int, args.photo_seeds.split(","))]
    for index, (scene, seed) in enumerate(realisations):
        name, overrides = scene_overrides(scene, seed, args.photo_variant)
        label = f"{scene} {realisation_folder(seed, args.photo_variant)}"
        folder = args.data / scene / realisation_folder(seed, args.photo_variant)
        folder.mkdir(parents=True, exist_ok=True)
        ckpt = None
        # the order alternates between realisations: a drift of the machine's speed
        # favours no method
        for method in methods if index % 2 == 0 else methods[::-1]:
            if method == "rte_paper" and scene not in args.paper_on.split(","):
                continue
            result = folder / f"{method}.json"
            if result.is_file():
                given = json.loads(result.read_text()).get("given_to_all", [])
                if given != args.given_to_all:
                    print(f"{result} was run with --given-to-all {given or 'none'}, not "
                          f"{args.given_to_all or 'none'}: pass the same overrides, or "
                          "another --data folder for the changed comparison.", file=sys.stderr)
                    raise SystemExit(2)
                print(f"{label} {method}: done already", flush=True)
                continue
            ckpt = ckpt or ea_checkpoint(name, args.preset, overrides)
            record = run_method(folder / method, [*METHODS[method], *args.given_to_all],
                                overrides, ckpt, args.budget_s, args.every_s, args.preset,
                                args.out, {"scene": scene, "photo_seed": seed,
                                           "method": method, "photo_variant": args.photo_variant,
                                           "code": code, "given_to_all": args.given_to_all})
            print(summary_line(f"{label} {method}", record), flush=True)


# ------------------------------------------------------------------------- redraw
def read_results(data: Path) -> dict[tuple[str, str, str], dict]:
    """(scene, realisation (:func:`realisation_folder`), method) -> the run's record, with
    its curve as arrays."""
    out = {}
    for path in sorted(data.glob("*/photo*/*.json")):
        record = read_record(path)
        photos = realisation_folder(int(record["photo_seed"]),
                                    record.get("photo_variant", "auto"))
        out[(record["scene"], photos, record["method"])] = record
    return out


def seconds_to_reach(curve: dict, key: str, level: float) -> float:
    """Training seconds at which a curve first reaches ``level`` or lower (nan: never)."""
    hit = np.nonzero(curve[key] <= level)[0]
    return float(curve["wall_s"][hit[0]]) if hit.size else math.nan


def mean_spread(values: list[float]) -> str:
    """``mean ± sample standard deviation`` over realisations (the value alone for one)."""
    values = [v for v in values if not math.isnan(v)]
    if not values:
        return "-"
    mean = statistics.fmean(values)
    return f"{mean:.3f}" if len(values) == 1 else f"{mean:.3f} ± {statistics.stdev(values):.3f}"


def scene_means(results: dict, method: str, key: str) -> dict[str, float]:
    """Scene -> the mean over its realisations of one end metric of one method."""
    by: dict[str, list[float]] = {}
    for (scene, _, m), rec in results.items():
        value = rec["metrics"].get(key, math.nan)
        if m == method and not math.isnan(value):
            by.setdefault(scene, []).append(value)
    return {scene: sum(v) / len(v) for scene, v in by.items()}


def compare(rte: dict[str, float], dpt: dict[str, float], difference: bool) -> str:
    """Stage 2 against the baseline over the scenes both have: the geometric mean of the
    per-scene ratios (or the mean of the differences), their range and the scenes where
    stage 2 is better (a lower error, or a higher PSNR with ``difference``)."""
    scenes = sorted(set(rte) & set(dpt))
    if not scenes:
        return "-"
    if difference:
        values = [rte[s] - dpt[s] for s in scenes]
        centre, better = sum(values) / len(values), sum(v > 0 for v in values)
        text = f"{centre:+.2f} dB ({min(values):+.2f} to {max(values):+.2f})"
    else:
        values = [rte[s] / dpt[s] for s in scenes]
        centre = math.exp(sum(math.log(v) for v in values) / len(values))
        better = sum(v < 1 for v in values)
        text = f"{centre:.2f}x ({min(values):.2f}-{max(values):.2f})"
    return f"{text}, {better}/{len(scenes)}"


def over_scenes(results: dict) -> list[str]:
    """Markdown lines: stage 2 against the baseline over the blind scenes and over all:
    for each property MSE and LPIPS the geometric mean of the per-scene ratios stage 2 /
    baseline (each scene's realisations averaged first; below 1: stage 2 lower), for PSNR
    the mean difference in dB; then the range and in how many scenes stage 2 is better."""
    keys = [*(f"mse_{k}_x100" for k in PROPERTIES), "psnr_novel", "lpips_novel"]
    head = ["scenes", *PROPERTIES, "PSNR novel", "LPIPS novel"]
    lines = ["Stage 2 / baseline per scene: geometric mean (range), scenes where stage 2 is "
             "better; PSNR: stage 2 minus baseline.", "",
             "| " + " | ".join(head) + " |", "|---|" + "---:|" * len(keys)]
    scenes = set(k[0] for k in results)
    means = {key: [scene_means(results, m, key) for m in ("rte", "dpt")] for key in keys}
    for label, group in (("blind", scenes & set(BLIND_SCENES)), ("all", scenes)):
        cells = [label]
        for key in keys:
            rte, dpt = means[key]
            cells.append(compare({s: v for s, v in rte.items() if s in group},
                                 {s: v for s, v in dpt.items() if s in group},
                                 difference=key == "psnr_novel"))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def provenance(results: dict) -> list[str]:
    """Markdown lines: per realisation, the commits its records ran at, whether its methods
    started from the same EA weights (by their SHA-256; "not recorded" for records that
    predate it) and the machine's GEMM probe before each method's training (GFLOP/s)."""
    by: dict[tuple[str, str], dict[str, dict]] = {}
    for (scene, photos, method), rec in sorted(results.items()):
        by.setdefault((scene, photos), {})[method] = rec
    lines = ["| scene | photos | code | same EA weights | GEMM probe GFLOP/s before |",
             "|---|---|---|---|---|"]
    for (scene, photos), recs in by.items():
        codes = sorted({str(r.get("code", r.get("commit", "not recorded"))) for r in recs.values()})
        hashes = {r.get("ea_ckpt", {}).get("weights_sha256") for r in recs.values()}
        same = "not recorded" if None in hashes else ("yes" if len(hashes) == 1 else "NO")
        speed = ", ".join(f"{m} {r['machine']['before']['gemm_gflops']:.0f}"
                          for m, r in recs.items() if "machine" in r) or "not recorded"
        lines.append(f"| {scene} | {photos} | {', '.join(codes)} | {same} | {speed} |")
    return lines


def table(results: dict) -> str:
    """Markdown: per scene and method, the start's sigma_t and the end's property MSE x100
    and re-render metrics, mean and sample sd over photo realisations; then stage 2's and
    the baseline's time to reach each other's final sigma_t."""
    scenes = list(dict.fromkeys(k[0] for k in results))
    head = ["scene", "method", "realisations", "start sigma_t", "sigma_a", "sigma_s",
            "sigma_t", "g", "PSNR novel", "SSIM novel", "LPIPS novel", "noise floor", "steps"]
    lines = ["| " + " | ".join(head) + " |", "|---|---|" + "---:|" * (len(head) - 2)]
    for scene in scenes:
        for method in METHODS:
            recs = [r for (s, _, m), r in sorted(results.items()) if s == scene and m == method]
            if not recs:
                continue
            cells = [scene, LABELS[method], str(len(recs)),
                     mean_spread([float(r["curve"]["sigma_t"][0]) for r in recs])]
            for key in (*(f"mse_{k}_x100" for k in PROPERTIES), *EVAL_KEYS):
                cells.append(mean_spread([r["metrics"].get(key, math.nan) for r in recs]))
            cells.append(mean_spread([float(r["steps"]) for r in recs]).split(".")[0])
            lines.append("| " + " | ".join(cells) + " |")
    lines += ["", *over_scenes(results)]
    lines += ["", "| scene | photos | stage 2 s to the baseline's end sigma_t | baseline s to "
              "stage 2's end sigma_t | budget s |", "|---|---|---:|---:|---:|"]
    for (scene, photos, method), rte in sorted(results.items()):
        dpt = results.get((scene, photos, "dpt"))
        if method != "rte" or dpt is None:
            continue
        cells = []
        for own, other in ((rte, dpt), (dpt, rte)):
            t = seconds_to_reach(own["curve"], "sigma_t", other["metrics"]["mse_sigma_t_x100"])
            cells.append(f"never (> {own['seconds']:.0f})" if math.isnan(t) else f"{t:.0f}")
        lines.append(f"| {scene} | {photos} | {cells[0]} | {cells[1]} | {rte['budget_s']:.0f} |")
    lines += ["", *provenance(results)]
    return "\n".join(lines) + "\n"


def figure(results: dict, path: Path) -> Path:
    """Rows of scenes, columns of properties: MSE x100 against training seconds (log-log),
    one line per method and realisation, the baseline's best-so-far marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    scenes = list(dict.fromkeys(k[0] for k in results))
    realisations = sorted({k[1] for k in results})  # one line style each
    fig, axes = plt.subplots(len(scenes), len(PROPERTIES), squeeze=False,
                             figsize=(3.4 * len(PROPERTIES), 2.6 * len(scenes)))
    for row, scene in enumerate(scenes):
        for col, key in enumerate(PROPERTIES):
            ax = axes[row][col]
            for (s, photos, method), rec in sorted(results.items()):
                c = rec["curve"]
                ok = np.isfinite(c[key])
                if s != scene or not ok.any():
                    continue
                # log time has no zero: the start (step 0) is drawn at half the first interval
                t = np.maximum(c["wall_s"], c["wall_s"][c["wall_s"] > 0].min(initial=1.0) / 2)
                style = ("-", "--", ":", "-.")[realisations.index(photos) % 4]
                ax.plot(t[ok], c[key][ok], style, color=COLOURS[method], lw=1.2,
                        label=f"{LABELS[method]}, {photos}")
                ax.plot(t[ok][:1], c[key][ok][:1], "o", color=COLOURS[method], ms=3)
                if method == "dpt":
                    best = int(np.nanargmin(c[key]))
                    ax.plot(t[best], c[key][best], "*", color="k", ms=7)
            ax.set_xscale("log")
            ax.set_yscale("log")
            for axis in (ax.xaxis, ax.yaxis):
                axis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            # an error axis spanning under a decade has no labelled power of ten: its minor
            # ticks (2, 3, ... x 10^k) are labelled instead
            ax.yaxis.set_minor_formatter(matplotlib.ticker.LogFormatter(
                labelOnlyBase=False, minor_thresholds=(1, 0.4)))
            ax.tick_params(axis="y", which="minor", labelsize=7)
            ax.grid(True, which="both", alpha=0.3)
            ax.set_title(f"{scene}: {key} MSE x100", fontsize=9)
            if row == len(scenes) - 1:
                ax.set_xlabel("training seconds (the dot: the start)")
    handles = {}
    for ax in axes.flat:
        for line in ax.get_lines():
            if not line.get_label().startswith("_"):
                handles.setdefault(line.get_label(), line)
    fig.legend(handles.values(), handles.keys(), loc="lower center", fontsize=8,
               ncol=min(len(handles), 3), frameon=False, bbox_to_anchor=(0.5, 0.015))
    fig.text(0.01, 0.005, "*: the baseline's best value on the way (not selectable without "
             "the truth)", fontsize=7)
    fig.tight_layout(rect=(0, 0.04 + 0.025 * ((len(handles) + 2) // 3), 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="train, evaluate and record")
    run.add_argument("--scenes", default="default,heldout,heldout2,heldout3,heldout4")
    run.add_argument("--photo-seeds", default="0,1")
    run.add_argument("--photo-variant", default="auto",
                     help="the Mitsuba variant that renders new photos (scalar_rgb: the "
                          "fallback where LLVM is missing); its realisations are kept apart")
    run.add_argument("--methods", default="rte,dpt,rte_paper")
    run.add_argument("--paper-on", default="default", help="scenes that run rte_paper too")
    run.add_argument("--given-to-all", action="append", default=[], metavar="KEY=VALUE",
                     help="a training override given to every method alike (repeatable; e.g. "
                          "both methods' grid schedule); recorded, and a --data folder holds "
                          "one set of them")
    add_budget_arguments(run, budget_s=600.0, every_s=25.0)
    run.add_argument("--data", type=Path, default=DATA)
    run.add_argument("--out", type=Path, default=output_dir() / "benchmarks" / "comparison")
    redraw = sub.add_parser("redraw", help="figure and table from the recorded data")
    redraw.add_argument("--data", type=Path, default=DATA)
    redraw.add_argument("--figure", type=Path, default=FIGURE)
    redraw.add_argument("--table", type=Path, default=DATA / "table.md")
    args = parser.parse_args()
    if args.command == "run":
        unknown = [s for s in args.scenes.split(",") if s not in SCENES]
        if unknown:
            parser.error(f"--scenes: {', '.join(unknown)} unknown; known: {', '.join(SCENES)}.")
        run_all(args)
        return
    results = read_results(args.data)
    if not results:
        parser.error(f"no results under {args.data}: run `python -m benchmarks.fair_comparison "
                     "run` first.")
    text = table(results)
    args.table.write_text(text)
    print(text)
    print(f"figure: {figure(results, args.figure)}; table: {args.table}")


if __name__ == "__main__":
    main()
