"""Generative stage 2 per member: each member's property MSE at the start and the end, its
levers side by side.

For each stage-2 configuration (a name and its overrides, :data:`CONFIGS`) and seed,
``nrt-train stage=rte mode=generative scene=family`` at the preset, through the CLI, from
the generative stage-1 run of configuration ``--stage1`` (a name of
:data:`benchmarks.generative_stage1.CONFIGS`) and the same seed: the newest finished run
under the output folder whose saved config trains the same (however it was spelled), else a
new one. Every member's sigma_t, sigma_s, sigma_a and g MSE
x100 at the first validation (step 0: the stage as built from stage 1) and the last, its
end PSNR, and the run's training seconds go to ``--table`` (CSV), one row per member. A run
whose (stage1, config, preset, seed) rows exist is skipped, so a killed benchmark
continues; ``--summary`` prints per run the family's mean start and end, the members that
end below their start and the worst member's end / start, from the table alone.
``--from-run DIR`` adds the rows of a finished run instead of training one (its metrics
from ``csv/metrics.csv``, else from its TensorBoard scalars).

    python -m benchmarks.generative_stage2 [--preset cpu] [--stage1 default]
        [--seeds 0] [--configs default,two_a_step] [--table docs/data/generative_stage2.csv]
        [--from-run DIR --configs NAME --seeds S] [--summary]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from benchmarks import generative_stage1
from benchmarks.common import (
    append_rows,
    output_dir,
    read_table,
    run_like,
    train,
    unfinished_run_error,
    validation_rows,
)
from nrt.run_dirs import LAST_CKPT, read_run_info

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "docs" / "data" / "generative_stage2.csv"
FREE_OFFSETS = ["mode.latent.member_offsets=true", "mode.latent.offset_prior_weight=0",
                "mode.latent.light_offsets=true"]
"""Free feature offsets (no prior) for each member's medium and light."""
ANNEAL_SLOW = ["data.members_per_step=2", "budget.rte.steps=4500", "mode.latent.dim=16",
               *FREE_OFFSETS, "model.lr_final_factor=0.01", "model.lr.medium=1.0e-2",
               "model.lr.light=1.0e-2"]
"""Two members a step from a d_z = 16 stage 1, free offsets, every rate annealed to 1/100
of its start from half the medium's and the light's: the setting that takes every member
below its start (docs/generative.md); the levers after it add to it."""
ANNEAL_SLOW_LONG = [*(o for o in ANNEAL_SLOW if not o.startswith("budget.rte.steps=")),
                    "budget.rte.steps=9000"]
"""The same in twice the steps, the anneal stretched over them."""
CONFIGS = {
    "default": [],
    # two members a step (each drawn member gets 8x the photo rays of a step over all 16),
    # in three times the steps: each member sees 3x the photo rays of the default run
    "two_a_step": ["data.members_per_step=2", "budget.rte.steps=4500"],
    # and the medium's and the light's decoders of twice the features and width and one
    # more hidden layer: whether the shared decoders' capacity limits the members
    "two_a_step_wide": ["data.members_per_step=2", "budget.rte.steps=4500",
                        "model.medium.features=32", "model.medium.hidden=128",
                        "model.medium.layers=2", "model.light_field.features=32",
                        "model.light_field.hidden=128", "model.light_field.layers=2"],
    # two members a step from a stage 1 of d_z = 16 (--stage1 latent_dim16): the codes the
    # decoders read span the members' corrections instead of a 4-dimensional family of them
    "two_a_step_dim16": ["data.members_per_step=2", "budget.rte.steps=4500",
                         "mode.latent.dim=16"],
    # and a feature offset per member under its prior: each member's medium can leave the
    # decoders' shared family, as a single-scene medium's free grid does
    "two_a_step_dim16_offsets": ["data.members_per_step=2", "budget.rte.steps=4500",
                                 "mode.latent.dim=16", "mode.latent.member_offsets=true"],
    # free offsets (no prior) for each member's medium and light: as free per member as
    # single-scene stage 2's grids, whether the shared decoders are what holds members back
    "two_a_step_dim16_free_offsets": ["data.members_per_step=2", "budget.rte.steps=4500",
                                      "mode.latent.dim=16", *FREE_OFFSETS],
    # the same in twice the steps: each member sees 1125 steps' photo rays, against the
    # 1500 of a single-scene run; whether the free offsets' end (20.8 on three seeds) is
    # the steps' or the setting's
    "two_a_step_dim16_free_offsets_long": ["data.members_per_step=2", "budget.rte.steps=9000",
                                           "mode.latent.dim=16", *FREE_OFFSETS],
    # free offsets at twice the medium's and the light's rates: each member's offsets take
    # a step only when the member is drawn (2 of 16 steps), and the 9000-step run still falls
    # at its end, as a rate-limited fit does (at `tiny`, half the medium's rate ends higher)
    "two_a_step_dim16_free_offsets_fast": ["data.members_per_step=2", "budget.rte.steps=4500",
                                           "mode.latent.dim=16", *FREE_OFFSETS,
                                           "model.lr.medium=4.0e-2", "model.lr.light=4.0e-2"],
    # free offsets with every rate decaying to 1/100 of its start instead of 1/10: the
    # validations of the 9000-step run swing by up to 50 % from one to the next, and each
    # run's last stretch, where the rate is least, brings its largest steady fall
    "two_a_step_dim16_free_offsets_anneal": ["data.members_per_step=2", "budget.rte.steps=4500",
                                             "mode.latent.dim=16", *FREE_OFFSETS,
                                             "model.lr_final_factor=0.01"],
    # and half the medium's and the light's start rates: twice them undid the offsets' gain
    "two_a_step_dim16_free_offsets_anneal_slow": ANNEAL_SLOW,
    # and twin rays through every photo ray's pixel (an unbiased photo loss): a single ray's
    # squared error adds its variance inside the pixel, a pull toward media blurred at the
    # pixel's scale, and the reconstructions hold about twice the floor's mass where the
    # true media are empty
    "two_a_step_dim16_free_offsets_anneal_slow_twins": [*ANNEAL_SLOW,
                                                        "budget.rte.photo_twins=512"],
    # and the extinction prior saturated at 0.5 (s log(1 + sigma_t / s)) at ten times the
    # weight: dense cores pushed about as before, thin cells up to ten times harder; the
    # reconstructions hold 8.6x the truth's extinction where it is thin (< 0.5), a halo of
    # the stage-1 density's blur that the photos see only faintly
    "two_a_step_dim16_free_offsets_anneal_slow_sparse": [
        *ANNEAL_SLOW, "losses.objectives.extinction_prior.saturation=0.5",
        "losses.weights.extinction_prior=1.0e-3"],
    # and the extinction prior at 3e-5 instead of 1e-4 (a weight the path-tracing
    # baseline's tuning tried, docs/baseline.md): single-scene stage 2 started from the
    # truth of a dense member ends at 26.6 with the prior at 1e-4 (its dense cores' extinction
    # 0.69 below the truth's on average) and at 16.3 without it; the reconstructions' dense
    # cores hold 0.91x the truth's extinction
    "two_a_step_dim16_free_offsets_anneal_slow_prior3e-5": [
        *ANNEAL_SLOW, "losses.weights.extinction_prior=3.0e-5"],
    # in twice the steps, the anneal stretched over them: each member drawn on 1125 steps
    # against 562; stage 2 holds a sharp medium when started from the truth and from a
    # blurred start removes part of the blur in its steps
    "two_a_step_dim16_free_offsets_anneal_slow_long": ANNEAL_SLOW_LONG,
    # and twin photo rays: the two levers that each brought the reconstructions closest
    "two_a_step_dim16_free_offsets_anneal_slow_long_twins": [*ANNEAL_SLOW_LONG,
                                                             "budget.rte.photo_twins=512"],
    # and noise on the codes (0.7 of their spread, as far from a code as Scott's smoothed
    # bootstrap draws): the decoders trained on codes around each member, where a sampler
    # draws, not only at the 16 codes (folded at the codes, the decoder's media leave the
    # family a short way from them)
    "two_a_step_dim16_free_offsets_anneal_slow_long_twins_code_noise": [
        *ANNEAL_SLOW_LONG, "budget.rte.photo_twins=512", "mode.latent.code_noise=0.7"],
    # and Adam stepping each member's code and offsets only on its own steps: plain Adam
    # moves an undrawn member by its last draw's momentum, about sqrt(16 / 2) learning
    # rates for each gradient it gets, where a single scene's parameter moves by about one
    "two_a_step_dim16_free_offsets_anneal_per_member_adam": [
        "data.members_per_step=2", "budget.rte.steps=4500", "mode.latent.dim=16",
        *FREE_OFFSETS, "model.lr_final_factor=0.01", "mode.latent.per_member_adam=true"],
    # twice `tiny`'s 900 steps, every member a step: each of its K = 4 members then sees
    # half the photo rays a single-scene run of 900 steps gives one scene, not a quarter
    "twice_the_steps_tiny": ["budget.rte.steps=1800"],
    # the medium's and the codes' rates ramped in over a quarter of the run after the light's
    # warm-up: their first full-rate Adam steps move every member's medium at once
    "medium_rampup": ["model.medium_rampup=0.25"],
    # half the medium's rate: whether a member that starts well drifts less
    "half_medium_rate": ["model.lr.medium=1.0e-2"],
    # free offsets at the default's steps, every member a step: whether they take every
    # member below its start at `tiny` too
    "free_offsets": FREE_OFFSETS,
}
"""The stage-2 configurations measured, by name: their overrides of the generative defaults."""
PROPERTIES = ("sigma_t", "sigma_s", "sigma_a", "g")
FIELDS = ("stage1", "config", "preset", "seed", "member",
          *(f"{p}_{when}" for p in PROPERTIES for when in ("start", "end")),
          "psnr_end", "train_s", "steps", "overrides")


def run_rows(run: Path, stage1: str, config: str, preset: str, seed: int) -> list[dict]:
    """The table's rows of a finished generative stage-2 run: one per member."""
    rows = validation_rows(run)
    first, last = rows[0], rows[-1]
    info = read_run_info(run)
    members = len(info["members"])
    out = []
    for k in range(members):
        row = {"stage1": stage1, "config": config, "preset": preset, "seed": seed,
               "member": k, "psnr_end": f"{last[f'val/psnr_member{k}']:.3f}",
               "train_s": f"{info['final_metrics']['time/wall_s']:.1f}",
               "steps": info["finished_step"], "overrides": " ".join(CONFIGS.get(config, []))}
        for prop in PROPERTIES:
            key = f"val/mse_{prop}_x100_member{k}"
            row[f"{prop}_start"], row[f"{prop}_end"] = f"{first[key]:.4f}", f"{last[key]:.4f}"
        out.append(row)
    return out


def stage1_checkpoint(stage1: str, preset: str, seed: int) -> Path:
    """The last checkpoint of the newest finished generative stage-1 run under the output
    folder that trains what configuration ``stage1`` at ``preset`` and ``seed`` does (as
    :mod:`benchmarks.generative_stage1` trains it); a new run when there is none."""
    overrides = ["scene=family", "mode=generative", *generative_stage1.CONFIGS[stage1],
                 f"seed={seed}"]
    return (run_like("ea", preset, overrides, logger="[csv]") / LAST_CKPT).resolve()


def summary(rows: list[dict]) -> str:
    """Per run (stage1, config, preset, seed): the members' mean sigma_t and sigma_s MSE x100
    at the start and the end, how many members end below their start, the worst member's
    end / start."""
    lines = ["| stage 1 | stage 2 | preset | seed | sigma_t start -> end | sigma_s start -> end "
             "| members below start | worst end / start | training s |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    runs: dict[tuple[str, ...], list[dict]] = {}
    for row in rows:
        runs.setdefault((row["stage1"], row["config"], row["preset"], row["seed"]),
                        []).append(row)

    def mean(members: list[dict], key: str) -> float:
        return statistics.fmean(float(m[key]) for m in members)

    for (stage1, config, preset, seed), members in runs.items():
        ratios = [float(m["sigma_t_end"]) / float(m["sigma_t_start"]) for m in members]
        lines.append(
            f"| {stage1} | {config} | {preset} | {seed} | {mean(members, 'sigma_t_start'):.1f} "
            f"-> {mean(members, 'sigma_t_end'):.1f} | {mean(members, 'sigma_s_start'):.1f} -> "
            f"{mean(members, 'sigma_s_end'):.1f} | {sum(r < 1 for r in ratios)} / "
            f"{len(ratios)} | {max(ratios):.2f} | {members[0]['train_s']} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--stage1", default="default",
                        choices=[c for c in generative_stage1.CONFIGS if c != "single"])
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--configs", default=",".join(CONFIGS))
    parser.add_argument("--table", type=Path, default=TABLE)
    parser.add_argument("--from-run", type=Path, default=None,
                        help="add a finished run's rows (one --configs name, one --seeds)")
    parser.add_argument("--summary", action="store_true", help="print the table and stop")
    args = parser.parse_args()
    if args.summary:
        print(summary(read_table(args.table)))
        return
    configs, seeds = args.configs.split(","), [int(s) for s in args.seeds.split(",")]
    unknown = [c for c in configs if c not in CONFIGS]
    if unknown:
        parser.error(f"--configs: unknown configuration {unknown[0]!r}; the known ones are "
                     f"{', '.join(CONFIGS)} (benchmarks/generative_stage2.py).")
    if args.from_run is not None:
        if len(configs) != 1 or len(seeds) != 1:
            parser.error("--from-run: name the run's one configuration (--configs) and its "
                         "seed (--seeds).")
        problem = unfinished_run_error(args.from_run)
        if problem:
            parser.error(f"--from-run: {problem}")
        append_rows(args.table, FIELDS, run_rows(args.from_run, args.stage1, configs[0],
                                         args.preset, seeds[0]))
        print(summary(read_table(args.table)))
        return
    done = {(r["stage1"], r["config"], r["preset"], r["seed"])
            for r in read_table(args.table)}
    for seed in seeds:
        for config in configs:
            if (args.stage1, config, args.preset, str(seed)) in done:
                continue
            ckpt = stage1_checkpoint(args.stage1, args.preset, seed)
            run, _ = train("rte", output_dir(), args.preset,
                           ["scene=family", "mode=generative", f"init.ea_ckpt={ckpt}",
                            *CONFIGS[config], f"seed={seed}"])
            append_rows(args.table, FIELDS, run_rows(run, args.stage1, config, args.preset, seed))
            print(summary([r for r in read_table(args.table)
                           if (r["config"], r["seed"]) == (config, str(seed))]), flush=True)


if __name__ == "__main__":
    main()
