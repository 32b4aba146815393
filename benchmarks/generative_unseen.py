"""How new media of a family score in FID against its members' photos, set by set: what a
sampler that draws new members exactly as the family does scores, with its spread over
draws of the media as well as over the FID's crops.

``nrt-sample fid.unseen_reference=true`` and :mod:`benchmarks.generative_sampling` score one
set of new media (the ``--n`` seeds after the members'). This benchmark scores several
disjoint sets of ``--n`` (set j: the seeds ``scene.seed + K + j n`` onward,
:func:`~nrt.evaluation.sample.unseen_media`; set 0 is the one the others score) and the
members' true media (the ``truth`` reference), rendered and cropped as ``nrt-sample``
renders its samples (the held-out cameras under the training and the held-back sky, the
family's spp, render seeds 1 + n + i), each scored on every FID seed against the same real
crops. Nothing is trained or decoded: ``--from-run`` names the family (a finished
generative stage-2 run's, with its scene config). Beside FID, each set's mean sigma_t MSE
x100 to the nearest member's true medium. A row per (run, set, seed) in ``--table``; rows
already there are skipped; ``--summary`` prints the table.

    python -m benchmarks.generative_unseen --from-run DIR [--label NAME] [--sets 0,1,2,3]
        [--seeds 0,1,2] [--n 16] [--table docs/data/generative_unseen.csv] [--summary]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from benchmarks.common import append_rows, read_table
from benchmarks.generative_sampling import (
    COLUMNS,
    add_run_arguments,
    checked_run,
    family_scoring,
    nearest,
    spread,
)

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "docs" / "data" / "generative_unseen.csv"
FIELDS = ("label", "run", "set", "first_seed", "seed", "n",
          *(f"fid_{col}" for col in COLUMNS), *(f"fid_{col}_truth" for col in COLUMNS),
          "nearest_truth", "members_apart")
"""The table's columns: FID of the set and of the true media under each sky, the set's
distance to the nearest member's true medium and the members' own spacing."""


def measure(run: Path, label: str, sets: list[int], seeds: list[int], n: int,
            table: Path) -> None:
    """The rows of ``run``'s family for every (set, seed) not yet in ``table``."""
    from nrt.evaluation.sample import unseen_media

    done = {(r["run"], r["set"], r["seed"], r["n"]) for r in read_table(table)}
    todo = [(j, s) for j in sets for s in seeds if (str(run), str(j), str(s), str(n)) not in done]
    if not todo:
        return
    scoring, _ = family_scoring(run, n)
    data = scoring.data
    members = int(data.scene["family"]["members"])
    # unseen_media refuses a config that does not draw the family again, before any render
    media = {j: unseen_media(data, n, start=j * n) for j in sorted({j for j, _ in todo})}
    references = {"truth": scoring.renders(data.truths),
                  **{j: scoring.renders(m) for j, m in media.items()}}
    apart = statistics.fmean(nearest(data.truths, data.truths, data.effects, skip_self=True))
    near = {j: statistics.fmean(nearest(m, data.truths, data.effects))
            for j, m in media.items()}
    for seed in sorted({s for _, s in todo}):
        scores = scoring.scorer(seed, references).references
        rows = [{"label": label, "run": str(run), "set": j,
                 "first_seed": int(data.scene["seed"]) + members + j * n, "seed": seed, "n": n,
                 **{f"fid_{col}": f"{scores[j][col]:.3f}" for col in COLUMNS},
                 **{f"fid_{col}_truth": f"{scores['truth'][col]:.3f}" for col in COLUMNS},
                 "nearest_truth": f"{near[j]:.4f}", "members_apart": f"{apart:.4f}"}
                for j, s in todo if s == seed]
        append_rows(table, FIELDS, rows)
        print(summary(read_table(table)), flush=True)


def summary(rows: list[dict]) -> str:
    """Per (label, set) and over all sets of a label: FID of the new media and of the true
    media under both skies (mean ± sd over the rows), the range of their ratio seed by seed,
    and the sets' distance to the nearest true medium."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in sorted(rows, key=lambda r: int(r["set"])):
        groups.setdefault((r["label"], r["set"]), []).append(r)
    for r in rows:
        groups.setdefault((r["label"], "all"), []).append(r)
    groups = dict(sorted(groups.items(), key=lambda item: item[0][0]))  # by label, stable
    lines = ["| run | set | rows | FID new media: train | novel | truth: train | novel "
             "| x truth: train | novel | nearest truth | members apart |",
             "|---|---|---:|" + "---:|" * 8]
    for (label, name), group in groups.items():
        def values(key: str, group=group) -> list[float]:
            return [float(r[key]) for r in group]

        def ratio(col: str, group=group) -> str:
            r = [float(g[f"fid_{col}"]) / float(g[f"fid_{col}_truth"]) for g in group]
            return f"{min(r):.2f}-{max(r):.2f}"

        lines.append(f"| {label} | {name} | {len(group)} | " + " | ".join(
            [*(spread(values(k)) for k in ("fid_train", "fid_novel", "fid_train_truth",
                                           "fid_novel_truth")),
             ratio("train"), ratio("novel"), spread(values("nearest_truth")),
             spread(values("members_apart"))]) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_run_arguments(parser)
    parser.add_argument("--sets", default="0,1,2,3", help="the sets of new media, from 0")
    parser.add_argument("--seeds", default="0,1,2", help="FID seeds (the crops)")
    parser.add_argument("--n", type=int, default=16, help="media per set")
    parser.add_argument("--table", type=Path, default=TABLE)
    parser.add_argument("--summary", action="store_true", help="print the table and stop")
    args = parser.parse_args()
    if args.summary:
        print(summary(read_table(args.table)))
        return
    try:
        sets = [int(j) for j in args.sets.split(",")]
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        parser.error(f"--sets {args.sets} / --seeds {args.seeds}: give comma-separated "
                     "integers, such as 0,1,2.")
    if min(sets) < 0 or args.n < 1:
        parser.error(f"--sets {args.sets} / --n {args.n}: sets count from 0, and a set holds "
                     "at least one medium.")
    run, label = checked_run(parser, args)
    measure(run, label, sets, seeds, args.n, args.table)


if __name__ == "__main__":
    main()
