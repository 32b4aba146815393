"""What the quickstart spends its minutes on: both stages as they run at
``--preset`` (``cpu``), against spending the same minutes on more stage-2 steps,
more stage-1 steps, or finer photos, per scene and seed.

    python -m benchmarks.quickstart_spend [--options as_is,rte_steps,ea_steps,fine]
        [--scenes default,heldout2] [--seeds 0] [--rte-steps 2500] [--ea-steps 3000]
        [--preset cpu] [--fine-preset cpu_fine] [--table docs/data/quickstart_spend.csv]

Options, each a whole quickstart (the photos, stage 1, stage 2 from its checkpoint, one seed
for both stages):

- ``as_is``: ``--preset`` (``cpu``: 1500 steps each);
- ``rte_steps``: stage 2 for ``--rte-steps`` steps (stage 1 is ``as_is``'s: the same run);
- ``ea_steps``: stage 1 for ``--ea-steps`` steps;
- ``fine``: ``--fine-preset`` (``cpu_fine``: 128 x 128 photos, 1024 photo rays).

A row per option, scene and seed in ``--table``: the photos' rendering seconds (``nrt-data``
wall time, once per preset and scene, into the benchmark's own dataset folder; kept in
``render_s.json`` there), each stage's training seconds and the sum, stage 1's held-out PSNR
and density
correlation, stage 2's start (its first validated sigma_t MSE x100: the EA density's), its
property MSEs x100 and held-out PSNR, the run folders and the commit.
Rows already in the table are skipped, and a stage-1 run recorded there is reused by the
options that share it, so a killed benchmark continues. Runs go under
``<output dir>/quickstart_spend`` (the table names them relative to it), its datasets in
``datasets/`` there; one training at a time.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

from benchmarks.common import (
    SCENES,
    commit_of,
    output_dir,
    run_cli,
    run_finals,
    series,
    train,
)
from nrt.run_dirs import LAST_CKPT

EA_KEPT = {"ea_psnr": "val/psnr", "ea_density_corr": "val/density_corr"}
RTE_KEPT = {"psnr_heldout": "val/psnr", "mse_sigma_a_x100": "val/mse_sigma_a_x100",
            "mse_sigma_s_x100": "val/mse_sigma_s_x100",
            "mse_sigma_t_x100": "val/mse_sigma_t_x100", "mse_g_x100": "val/mse_g_x100"}
COLUMNS = ["option", "scene", "seed", "preset", "ea_steps", "rte_steps", "render_s",
           "ea_train_s", "rte_train_s", "total_train_s", *EA_KEPT, "start_sigma_t_x100",
           *RTE_KEPT, "ea_over", "ea_run", "rte_run", "code"]


def options(preset: str, fine: str, rte_steps: int, ea_steps: int
            ) -> dict[str, tuple[str, list[str], list[str]]]:
    """Option name -> (preset, stage-1 overrides, stage-2 overrides)."""
    return {"as_is": (preset, [], []),
            "rte_steps": (preset, [], [f"budget.rte.steps={rte_steps}"]),
            "ea_steps": (preset, [f"budget.ea.steps={ea_steps}"], []),
            "fine": (fine, [], [])}


def write_table(table: Path, rows: list[dict]) -> None:
    """``rows`` as the CSV ``table`` with :data:`COLUMNS`, rewritten whole: a row written
    before a column existed gets it blank."""
    with table.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS, restval="")
        writer.writeheader()
        writer.writerows(rows)


def rendering_seconds(out: Path, data_dir: Path, preset: str, scene: str) -> float:
    """The wall seconds of ``nrt-data`` drawing ``scene``'s photos at ``preset`` into
    ``data_dir``: measured at the first call, then read from ``data_dir/render_s.json``."""
    record = data_dir / "render_s.json"
    times = json.loads(record.read_text()) if record.exists() else {}
    key = f"{preset}/{scene}"
    if key not in times:
        times[key] = round(run_cli("data", [f"preset={preset}", *SCENES[scene],
                                            f"paths.data_dir={data_dir}",
                                            "render.progress=false"], out), 1)
        record.write_text(json.dumps(times, indent=1))
    return times[key]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--options", default="as_is,rte_steps,ea_steps,fine")
    parser.add_argument("--scenes", default="default,heldout2")
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--preset", default="cpu", help="the as_is options' preset")
    parser.add_argument("--fine-preset", default="cpu_fine", help="the option fine's preset")
    parser.add_argument("--rte-steps", type=int, default=2500)
    parser.add_argument("--ea-steps", type=int, default=3000)
    parser.add_argument("--table", type=Path, default=Path("docs/data/quickstart_spend.csv"))
    args = parser.parse_args()
    table = list(csv.DictReader(args.table.open())) if args.table.exists() else []
    done = {(r["option"], r["scene"], r["seed"]) for r in table}
    chosen = options(args.preset, args.fine_preset, args.rte_steps, args.ea_steps)
    out = output_dir() / "quickstart_spend"
    data_dir = out / "datasets"  # its own: the photos' rendering is part of a quickstart
    out.mkdir(parents=True, exist_ok=True)
    code = commit_of(Path(__file__).resolve().parent.parent)
    for scene in args.scenes.split(","):
        for seed in args.seeds.split(","):
            for name in args.options.split(","):
                if (name, scene, seed) in done:
                    continue
                preset, ea_over, rte_over = chosen[name]
                photos = SCENES[scene]
                render_s = rendering_seconds(out, data_dir, preset, scene)
                ea_key = (preset, scene, seed, " ".join(ea_over))
                ea_run = next((out / r["ea_run"] for r in table
                               if (r["preset"], r["scene"], r["seed"], r["ea_over"]) == ea_key
                               and (out / r["ea_run"] / LAST_CKPT).exists()), None)
                if ea_run is None:
                    ea_run, _ = train("ea", out, preset, [*photos, *ea_over, f"seed={seed}"],
                                      data_dir=data_dir)
                rte_run, _ = train("rte", out, preset, [
                    *photos, *rte_over, f"seed={seed}",
                    f"init.ea_ckpt={(ea_run / LAST_CKPT).resolve()}"], data_dir=data_dir)
                ea, rte = run_finals(ea_run, EA_KEPT), run_finals(rte_run, RTE_KEPT)
                row = {"option": name, "scene": scene, "seed": seed, "preset": preset,
                       "ea_steps": ea["steps"], "rte_steps": rte["steps"],
                       "render_s": render_s,
                       "ea_train_s": ea["train_s"], "rte_train_s": rte["train_s"],
                       "total_train_s": round(ea["train_s"] + rte["train_s"], 1),
                       **{k: ea.get(k, "") for k in EA_KEPT},
                       "start_sigma_t_x100": round(series(rte_run, RTE_KEPT[
                           "mse_sigma_t_x100"])[0], 4),
                       **{k: rte.get(k, "") for k in RTE_KEPT}, "ea_over": " ".join(ea_over),
                       "ea_run": str(ea_run.relative_to(out)),
                       "rte_run": str(rte_run.relative_to(out)), "code": code}
                table.append({k: str(v) for k, v in row.items()})
                write_table(args.table, table)
                print(f"{name} {scene} seed {seed}: stage 1 {ea['train_s']} s, stage 2 "
                      f"{rte['train_s']} s, sigma_t {rte.get('mse_sigma_t_x100')}", flush=True)


if __name__ == "__main__":
    main()
