"""The paper's evaluation at CPU scale: Tables 1-3 over benchmark sets of scenes, one command.

``run``: for every scene of the sets in ``benchmarks/paper_tables.yaml`` (an isotropic and an
anisotropic set drawn by the paper's recipe from seeds nothing was tuned on; the first
``--iso`` / ``--aniso`` of each), the dataset and its EA checkpoint (rendered and trained
once, found again under ``outputs/`` by the scene's name), then stage 2 and the baseline
for ``--budget-s`` training seconds each from that one checkpoint, each scored by
``nrt-eval``'s Mitsuba re-render under the held-back sky (``benchmarks.equal_time``); on the
first ``ablation_scenes`` isotropic scenes, the ablations at the same time. Every run leaves
``<data>/<set>/<scene>/<method>.{csv,json}`` (the JSON names the code's commit); a run whose
JSON exists is reused, so a killed benchmark continues where it stopped. One progress line per
run says where it is and about how long is left. For the first scene of each set, the media
of both methods and the truth are kept as small 32^3 grids for the slices figure.

``redraw``: Table 1 (isotropic set: stage 2 and the baseline per scene, mean ± std over the
scenes, seconds), Table 2 (anisotropic set, g scored weighted by the true sigma_s), Table 3
(ablations) as Markdown and CSV, the paper's numbers beside them (not comparable: GPU, 128^3,
256 px, 450 views), and the slices figures, from the recorded files alone.

    python -m benchmarks.paper_tables run [--iso 8] [--aniso 8] [--preset cpu]
        [--budget-s 600] [--every-s 50] [--ablation-scenes N] [--ablations a,b]
        [--methods rte,dpt] [--ea-steps N] [--data DIR]
    python -m benchmarks.paper_tables redraw [--data DIR] [--figures DIR]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from benchmarks.common import add_budget_arguments, commit_of, ea_checkpoint, output_dir
from benchmarks.equal_time import PROPERTIES, read_record, run_method, summary_line
from benchmarks.quickstart_slices import small
from nrt.data.dataset import GROUND_TRUTH_FILE
from nrt.evaluation.media import read_medium
from nrt.run_dirs import RUN_FILE

ROOT = Path(__file__).resolve().parent.parent
SETS = Path(__file__).with_suffix(".yaml")
DATA = ROOT / "docs" / "data" / "paper_tables"
FIGURES = ROOT / "docs" / "figures"
SLICE_CELLS = 32
COLUMNS = (*(f"mse_{k}_x100" for k in PROPERTIES), "psnr_novel", "ssim_novel", "lpips_novel",
           "psnr_noise_floor_novel")
LABELS = {"rte": "stage 2 (nrt)", "dpt": "path tracing (baseline)",
          "no_photo_term": "stage 2 without the photos' term", "single_stage":
          "single stage (no EA density)", "single_scattering": "no learned scattered light",
          "paper": "the paper's formulation (SIREN)", "paper_grid": "the paper's, grid medium"}
NOT_COMPARABLE = "paper (not comparable: GPU, 128^3, 256 px, 450 views)"


def load_sets(path: Path = SETS) -> dict:
    return yaml.safe_load(path.read_text())


def scene_name(set_name: str, seed: int) -> str:
    return f"paper_{set_name}_{seed}"


def scene_overrides(set_name: str, phase: str, scene: dict) -> list[str]:
    """Hydra overrides of the default scene that make a set's scene."""
    return [f"scene.name={scene_name(set_name, scene['seed'])}", f"scene.seed={scene['seed']}",
            f"scene.medium.num_elements={scene['elements']}", f"scene.effects.phase={phase}",
            "scene.medium.g_range=[-0.5,0.5]"]


def planned_runs(sets: dict, n: dict[str, int], ablation_scenes: int, ablations: list[str],
                 methods: list[str] | None = None) -> list[tuple[str, dict, str, list[str]]]:
    """(set, scene, method, overrides) of every run, in order, scene by scene: each scene's
    methods (all of the sets file's, or ``methods``), then, on the first ``ablation_scenes``
    isotropic scenes, its ablations, so that a scene's runs share the EA checkpoint of one
    sitting (the records hash it)."""
    runs = []
    for set_name in ("iso", "aniso"):
        for i, scene in enumerate(sets["sets"][set_name]["scenes"][:n[set_name]]):
            runs += [(set_name, scene, m, o) for m, o in sets["methods"].items()
                     if methods is None or m in methods]
            if set_name == "iso" and i < ablation_scenes:
                runs += [(set_name, scene, a, sets["ablations"][a]) for a in ablations]
    return runs


def keep_slices(run: Path, folder: Path, method: str) -> None:
    """The run's medium (and, once, the truth of its dataset) as small grids for the figure."""
    np.savez_compressed(folder / f"{method}.npz", **small(read_medium(run), SLICE_CELLS))
    truth = folder / GROUND_TRUTH_FILE
    if not truth.is_file():
        dataset = Path(json.loads((run / RUN_FILE).read_text())["dataset_dir"])
        np.savez_compressed(truth, **small(read_medium(dataset / GROUND_TRUTH_FILE),
                                           SLICE_CELLS))


def time_left(later: list[tuple[str, dict, str, list[str]]], data: Path, current: str,
              spent: list[float], prepared: list[float], budget_s: float) -> str:
    """About how long the current run and the ``later`` ones take: each run as long as the
    timed runs so far took on average (at first its budget and two minutes of evaluation),
    each scene still without a record as long as the new scenes' renders and EA runs took
    (said apart until one was measured)."""
    each = sum(spent) / len(spent) if spent else budget_s + 120.0
    todo = [r for r in later if not (data / r[0] / scene_name(r[0], r[1]["seed"]) /
                                     r[2]).with_suffix(".json").is_file()]
    scenes = {scene_name(r[0], r[1]["seed"]) for r in todo} - {current}
    scenes = {s for s in scenes if not any(data.glob(f"*/{s}/*.json"))}
    minutes = each * (len(todo) + 1) / 60
    if not scenes:
        return f"{minutes:.0f} min left"
    new = f"{len(scenes)} new scene" + ("s" if len(scenes) > 1 else "")
    if prepared:
        minutes += sum(prepared) / len(prepared) * len(scenes) / 60
        return f"{minutes:.0f} min left (with the renders and EA runs of {new})"
    return f"{minutes:.0f} min left, and the renders and EA runs of {new}"


def run_all(args) -> None:
    sets = load_sets(args.sets)
    ablations = args.ablations.split(",") if args.ablations else list(sets["ablations"])
    methods = args.methods.split(",") if args.methods else list(sets["methods"])
    for flag, names, known in (("--ablations", ablations, sets["ablations"]),
                               ("--methods", methods, sets["methods"])):
        unknown = sorted(set(names) - set(known))
        if unknown:
            sys.exit(f"nrt: error: {flag}: {', '.join(unknown)} unknown; known: "
                     f"{', '.join(known)}.")
    n = {"iso": args.iso, "aniso": args.aniso}
    for set_name, count in n.items():
        size = len(sets["sets"][set_name]["scenes"])
        if not 0 <= count <= size:
            sys.exit(f"nrt: error: --{set_name}={count}: the set '{set_name}' of {args.sets} has "
                     f"{size} scenes; ask for 0 to {size}.")
    runs = planned_runs(sets, n, args.ablation_scenes, ablations, methods)
    firsts = {(s, sets["sets"][s]["scenes"][0]["seed"]) for s in n if n[s] > 0}
    spent: list[float] = []  # seconds of each timed run with its evaluation
    prepared: list[float] = []  # seconds of each new scene's render and EA run
    code = commit_of(ROOT)
    for i, (set_name, scene, method, stage_overrides) in enumerate(runs, 1):
        name = scene_name(set_name, scene["seed"])
        path = args.data / set_name / name / method
        if path.with_suffix(".json").is_file():
            print(f"[{i}/{len(runs)}] {name} {method}: done already", flush=True)
            continue
        new_scene = not any((args.data / set_name / name).glob("*.json"))
        if new_scene:
            print(f"[{i}/{len(runs)}] {name}: its dataset and EA run (found, or rendered and "
                  "trained now)", flush=True)
        overrides = scene_overrides(set_name, sets["sets"][set_name]["phase"], scene)
        start = time.perf_counter()
        ckpt = ea_checkpoint(name, args.preset, overrides, args.ea_steps)
        if new_scene and time.perf_counter() - start > 60.0:  # rendered or trained, not found
            prepared.append(time.perf_counter() - start)
        print(f"[{i}/{len(runs)}] {name} {method}: training {args.budget_s:.0f} s; about "
              f"{time_left(runs[i:], args.data, name, spent, prepared, args.budget_s)}",
              flush=True)
        start = time.perf_counter()
        record = run_method(path, stage_overrides, overrides, ckpt, args.budget_s, args.every_s,
                            args.preset, args.out, {"set": set_name, "scene": name,
                                                    "seed": scene["seed"], "method": method,
                                                    "code": code})
        spent.append(time.perf_counter() - start)
        if (set_name, scene["seed"]) in firsts and method in sets["methods"]:
            keep_slices(Path(record["run"]), path.parent, method)
        print(f"[{i}/{len(runs)}] " + summary_line(f"{name} {method}", record), flush=True)


# ------------------------------------------------------------------------- redraw
def read_results(data: Path) -> dict[str, dict[str, dict[str, dict]]]:
    """set -> scene -> method -> record."""
    out: dict[str, dict[str, dict[str, dict]]] = {}
    for path in sorted(data.glob("*/*/*.json")):
        record = read_record(path)
        out.setdefault(record["set"], {}).setdefault(record["scene"], {})[record["method"]] = \
            record
    return out


def mean_std(values: list[float]) -> str:
    """``mean ± std`` over scenes (the sample standard deviation; the value alone for one)."""
    values = [v for v in values if not math.isnan(v)]
    if not values:
        return "-"
    if len(values) == 1:
        return f"{values[0]:.3f}"
    return f"{np.mean(values):.3f} ± {np.std(values, ddof=1):.3f}"


def _cell(record: dict, key: str) -> float:
    return float(record["metrics"].get(key, math.nan))


def write_table(scenes: dict[str, dict[str, dict]], methods: list[str], title: str,
                paper: dict, md: Path) -> str:
    """A table's Markdown (per-scene rows, then mean ± std over the scenes per method, then
    the paper's numbers) and its CSV (per-scene rows) beside it."""
    head = ["scene", "method", *COLUMNS, "seconds", "steps"]
    rows = [[scene, m, *(f"{_cell(r[m], k):.5g}" for k in COLUMNS), f"{r[m]['seconds']:.0f}",
             str(r[m]["steps"])] for scene, r in scenes.items() for m in methods if m in r]
    with open(md.with_suffix(".csv"), "w", newline="") as f:
        csv.writer(f).writerows([head, *rows])
    short = [c.removeprefix("mse_").removesuffix("_x100") for c in COLUMNS]
    lines = [f"### {title}", "", "| scene | method | " + " | ".join(short) + " | seconds | steps |",
             "|---|---|" + "---:|" * (len(COLUMNS) + 2)]
    lines += ["| " + " | ".join([row[0], LABELS[row[1]], *row[2:]]) + " |" for row in rows]
    for m in methods:
        recs = [r[m] for r in scenes.values() if m in r]
        if recs:
            lines.append(f"| **mean ± std, {len(recs)} scenes** | {LABELS[m]} | " +
                         " | ".join(mean_std([_cell(r, k) for r in recs]) for k in COLUMNS) +
                         f" | {np.mean([r['seconds'] for r in recs]):.0f} | |")
    for m, values in paper.items():
        lines.append(f"| {NOT_COMPARABLE} | {LABELS[m]} | " +
                     " | ".join(str(values.get(k.removeprefix("mse_").removesuffix("_x100"), "-"))
                                for k in COLUMNS) + " | | |")
    codes = sorted({r[m].get("code", "not recorded") for r in scenes.values() for m in methods
                    if m in r})
    lines += ["", f"Code: {', '.join(codes)}."]
    text = "\n".join(lines) + "\n"
    md.write_text(text)
    return text


def redraw(data: Path, figures: Path, sets: dict) -> str:
    results = read_results(data)
    if not results:
        sys.exit(f"nrt: error: no results under {data}: run `python -m benchmarks.paper_tables "
                 "run` first.")
    paper = sets["paper"]
    methods = list(sets["methods"])
    out = []
    if "iso" in results:
        out.append(write_table(results["iso"], methods, "Table 1: isotropic set (MSE x100)",
                               paper["table1"], data / "table1.md"))
    if "aniso" in results:
        out.append(write_table(results["aniso"], methods, "Table 2: anisotropic set (g's MSE "
                               "weighted by the true sigma_s)", paper["table2"],
                               data / "table2.md"))
    ablated = {s: r for s, r in results.get("iso", {}).items()
               if any(a in r for a in sets["ablations"])}
    if ablated:
        out.append(write_table(ablated, ["rte", *sets["ablations"]], "Table 3: ablations of "
                               "stage 2 on isotropic scenes (MSE x100)", paper["table3"],
                               data / "table3.md"))
    for folder in sorted(data.glob("*/*")):
        kept = [folder / f"{m}.npz" for m in methods if (folder / f"{m}.npz").is_file()]
        if kept and (folder / GROUND_TRUTH_FILE).is_file():
            from nrt.cli.report import main as nrt_report

            png = figures / f"paper_tables_slices_{folder.name}.png"
            nrt_report(["--slices", *map(str, kept), "--truth", str(folder / GROUND_TRUTH_FILE),
                        "--labels", *(LABELS[p.stem] for p in kept), "--title",
                        f"{folder.name}: stage 2 and the baseline after equal time; "
                        f"grids resampled to {SLICE_CELLS}^3", "--out", str(png)])
            out.append(f"figure: {png}")
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="render, train, evaluate and record every scene")
    run.add_argument("--iso", type=int, default=8, help="scenes of the isotropic set")
    run.add_argument("--aniso", type=int, default=8, help="scenes of the anisotropic set")
    run.add_argument("--ablation-scenes", type=int, help="default: the sets file's")
    run.add_argument("--ablations", help="comma-separated names (default: all of the file's)")
    run.add_argument("--methods", help="comma-separated names (default: all of the file's)")
    add_budget_arguments(run, budget_s=600.0, every_s=50.0)
    run.add_argument("--ea-steps", type=int, help="steps of a new scene's EA run (default: "
                     "the preset's)")
    run.add_argument("--out", type=Path, default=output_dir() / "benchmarks" / "paper_tables")
    redraw_cmd = sub.add_parser("redraw", help="tables and figures from the recorded files")
    redraw_cmd.add_argument("--figures", type=Path, default=FIGURES)
    for p in (run, redraw_cmd):
        p.add_argument("--data", type=Path, default=DATA)
        p.add_argument("--sets", type=Path, default=SETS)
    args = parser.parse_args()
    if args.command == "run":
        if args.ablation_scenes is None:
            args.ablation_scenes = int(load_sets(args.sets)["ablation_scenes"])
        run_all(args)
    else:
        print(redraw(args.data, args.figures, load_sets(args.sets)))


if __name__ == "__main__":
    main()
