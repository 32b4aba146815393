"""What ``nrt-sample`` makes of a generative stage-2 run: the members' media once any offsets
are folded into the shared decoder, and the samples' FID against the true media's, a row a run.

For each seed, the generative stage-2 run that :mod:`benchmarks.generative_stage2` trains
for ``--stage1``, ``--config`` and that seed (the newest finished one under the output
folder whose saved config trains the same, else a new one), or ``--from-run DIR``; then
``nrt-sample run=<run> n=<n> fid.recon_reference=true`` through the CLI, the fold at its
default (2000 steps for a run with member offsets, none for one without). A row per run in
``--table`` (CSV): the fold's steps and objective before and after; the members' mean
sigma_t and sigma_s MSE x100 at stage 2's first validation and in ``nrt-sample``'s
reconstructions (each member's code through the decoder as sampled, folded where there
were offsets), the members whose reconstruction ends below their start and the worst
member's end / start; FID of the samples, of the true media and of the reconstructions
under the training and the held-back sky; the sampling seconds. A (stage1, config, preset,
seed) already in the table is skipped, so a killed benchmark continues; ``--summary``
prints the table's runs.

    python -m benchmarks.generative_samples [--preset cpu] [--stage1 latent_dim16]
        [--config two_a_step_dim16_free_offsets] [--seeds 2] [--n 16]
        [--from-run DIR --seeds S] [--table docs/data/generative_samples.csv] [--summary]
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from benchmarks import generative_stage1, generative_stage2
from benchmarks.common import (
    append_rows,
    output_dir,
    read_table,
    run_cli,
    run_like,
    unfinished_run_error,
    validation_rows,
)

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "docs" / "data" / "generative_samples.csv"
COLUMNS = ("train", "novel")
"""``nrt-sample``'s FID columns: the family's training sky and its held-back sky."""
REFERENCES = ("", "_truth", "_recon")
"""The samples, the true media and the members' reconstructions, rendered alike."""
FIELDS = ("stage1", "config", "preset", "seed", "n", "fold_steps", "fold_start", "fold_end",
          "sigma_t_start", "sigma_t_recon", "sigma_s_start", "sigma_s_recon",
          "members_below_start", "worst_recon_over_start",
          *(f"fid_{col}{ref}" for col in COLUMNS for ref in REFERENCES), "sample_s")


def sample_row(run: Path, report: dict, stage1: str, config: str, preset: str, seed: int
               ) -> dict:
    """The table's row of a stage-2 run and the ``metrics.json`` of its ``nrt-sample``."""
    start, metrics = validation_rows(run)[0], report["metrics"]
    members = report["members"]
    ratios = [m["mse_sigma_t_x100"] / start[f"val/mse_sigma_t_x100_member{m['member']}"]
              for m in members]

    def mean(key: str) -> float:
        return statistics.fmean(m[key] for m in members)

    def start_mean(prop: str) -> float:
        return statistics.fmean(start[f"val/mse_{prop}_x100_member{m['member']}"]
                                for m in members)

    return {"stage1": stage1, "config": config, "preset": preset, "seed": seed,
            "n": int(metrics["n_samples"]), "fold_steps": int(metrics.get("fold_steps", 0)),
            "fold_start": f"{metrics.get('fold_start', float('nan')):.4f}",
            "fold_end": f"{metrics.get('fold_end', float('nan')):.4f}",
            "sigma_t_start": f"{start_mean('sigma_t'):.4f}",
            "sigma_t_recon": f"{mean('mse_sigma_t_x100'):.4f}",
            "sigma_s_start": f"{start_mean('sigma_s'):.4f}",
            "sigma_s_recon": f"{mean('mse_sigma_s_x100'):.4f}",
            "members_below_start": sum(r < 1 for r in ratios),
            "worst_recon_over_start": f"{max(ratios):.4f}",
            **{f"fid_{col}{ref}": f"{metrics[f'fid_{col}_illumination{ref}']:.3f}"
               for col in COLUMNS for ref in REFERENCES},
            "sample_s": f"{metrics['wall_s'] + metrics.get('fold_s', 0.0):.1f}"}


def sample(run: Path, n: int) -> dict:
    """``nrt-sample run=<run> n=<n> fid.recon_reference=true``; its ``metrics.json``."""
    before = set(run.glob("sample/*/metrics.json"))
    run_cli("sample", [f"run={run}", f"n={n}", "fid.recon_reference=true"], output_dir())
    (new,) = set(run.glob("sample/*/metrics.json")) - before
    return json.loads(new.read_text())


def summary(rows: list[dict]) -> str:
    """The table's runs: the members' sigma_t from stage 2's start to the reconstructions
    sampled, and FID of samples, truth and reconstructions under both skies."""
    lines = ["| stage 1 | stage 2 | preset | seed | fold steps | sigma_t start -> recon "
             "| members below start | worst recon / start | FID samples (train / novel) "
             "| truth | recon |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(
            f"| {r['stage1']} | {r['config']} | {r['preset']} | {r['seed']} | "
            f"{r['fold_steps']} | {float(r['sigma_t_start']):.1f} -> "
            f"{float(r['sigma_t_recon']):.1f} | {r['members_below_start']} | "
            f"{float(r['worst_recon_over_start']):.2f} | "
            + " | ".join(" / ".join(f"{float(r[f'fid_{col}{ref}']):.1f}" for col in COLUMNS)
                         for ref in REFERENCES) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--stage1", default="latent_dim16",
                        choices=[c for c in generative_stage1.CONFIGS if c != "single"])
    parser.add_argument("--config", default="two_a_step_dim16_free_offsets",
                        choices=list(generative_stage2.CONFIGS))
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--n", type=int, default=16, help="media to sample")
    parser.add_argument("--table", type=Path, default=TABLE)
    parser.add_argument("--from-run", type=Path, default=None,
                        help="sample a finished generative stage-2 run (one --seeds)")
    parser.add_argument("--summary", action="store_true", help="print the table and stop")
    args = parser.parse_args()
    if args.summary:
        print(summary(read_table(args.table)))
        return
    seeds = [int(s) for s in args.seeds.split(",")]
    if args.from_run is not None:
        if len(seeds) != 1:
            parser.error("--from-run: name the run's one seed (--seeds).")
        problem = unfinished_run_error(args.from_run)
        if problem:
            parser.error(f"--from-run: {problem}")
    done = {(r["stage1"], r["config"], r["preset"], r["seed"]) for r in read_table(args.table)}
    for seed in seeds:
        if (args.stage1, args.config, args.preset, str(seed)) in done:
            continue
        run = args.from_run
        if run is None:
            ckpt = generative_stage2.stage1_checkpoint(args.stage1, args.preset, seed)
            run = run_like("rte", args.preset,
                           ["scene=family", "mode=generative", f"init.ea_ckpt={ckpt}",
                            *generative_stage2.CONFIGS[args.config], f"seed={seed}"])
        append_rows(args.table, FIELDS, [sample_row(run, sample(run, args.n), args.stage1,
                                                    args.config, args.preset, seed)])
        print(summary(read_table(args.table)), flush=True)


if __name__ == "__main__":
    main()
