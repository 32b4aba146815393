"""What a step of generative stage 2 costs against a single-scene step, as the family grows
(K members) and as steps draw fewer of them (``data.members_per_step`` M).

For each K of ``--members``: a short generative stage-1 run on the preset's family of K
members (``--ea-steps`` steps: a step's cost does not depend on how well stage 1 fitted,
only on the shapes), then, for each M of ``--per-step`` (``all``: every member a step; M
above K is skipped), ``benchmarks.profile_step --stage rte`` from that checkpoint with
``mode=generative scene=family scene.family.members=K data.members_per_step=M``; and once
the single scene (``default``) the same way. Each profile runs alone in its own process;
the unprofiled mean step time (ms), its ratio to the single scene's, the uncollided
refreshes in the profiled window and the largest components go to ``--table`` (CSV), one
row per run. A row already in the table is not run again, so a killed benchmark continues;
the single scene is re-run in every invocation (the ratios are taken within one run of the
benchmark, never against a number from another day). The members of a family of K are the
first K of the preset's family (their datasets are shared). ``--setting`` names the
generative settings both stages run under (:data:`SETTINGS`; a row records it).

    python -m benchmarks.generative_step_cost [--preset cpu] [--members 4,8,16]
        [--per-step all,2] [--steps 20] [--warmup 5] [--ea-steps 100]
        [--setting default] [--table docs/data/generative_step_cost.csv]
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.common import commit_of, output_dir, read_table, train
from nrt.run_dirs import LAST_CKPT

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "docs" / "data" / "generative_step_cost.csv"
FIELDS = ("preset", "setting", "members", "per_step", "step_ms", "single_scene_ms", "ratio",
          "refreshes", "largest", "code")
SETTINGS = {
    "default": [],
    # what recovers every member at `cpu` (docs/generative.md, "Two members a step"): codes
    # of 16 dimensions and a free feature offset per member for its medium and its light
    "dim16_free_offsets": ["mode.latent.dim=16", "mode.latent.member_offsets=true",
                           "mode.latent.offset_prior_weight=0",
                           "mode.latent.light_offsets=true"],
}
"""The generative settings measured, by name: their overrides of both stages' defaults."""


def family_overrides(members: int) -> list[str]:
    """The generative mode on the preset's family of ``members`` members."""
    return ["mode=generative", "scene=family", f"scene.family.members={members}"]


def profile(preset: str, steps: int, warmup: int, overrides: list[str],
            ea_ckpt: Path | None = None) -> dict:
    """``benchmarks.profile_step --stage rte`` in a process of its own; its report."""
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "profile.json"
        cmd = [sys.executable, "-m", "benchmarks.profile_step", "--stage", "rte", "--preset",
               preset, "--steps", str(steps), "--warmup", str(warmup), "--json", str(report),
               *(["--ea-ckpt", str(ea_ckpt)] if ea_ckpt else []),
               f"paths.data_dir={output_dir() / 'datasets'}", *overrides]
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        if proc.returncode != 0:
            sys.exit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
        return json.loads(report.read_text())


def largest(report: dict, n: int = 3) -> str:
    """The ``n`` largest components of a profile and their profiled ms per step."""
    rows = sorted(report["components"], key=lambda row: -row["ms"])[:n]
    return "; ".join(f"{row['component']} {row['ms']:.1f}" for row in rows)


def pending(rows: list[dict], preset: str, members: int, per_step: list[str],
            setting: str = "default") -> list[str]:
    """The members-a-step settings of ``per_step`` (``all`` or a number) still to run for a
    family of ``members`` at ``preset`` under ``setting``: neither in ``rows`` already (a
    row without a setting is the default's) nor above K."""
    done = {r["per_step"] for r in rows
            if (r["preset"], r["members"], r.get("setting") or "default")
            == (preset, str(members), setting)}
    return [m for m in per_step if m not in done and (m == "all" or int(m) <= members)]


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--members", default="4,8,16")
    parser.add_argument("--per-step", default="all,2")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--ea-steps", type=int, default=100)
    parser.add_argument("--setting", default="default", choices=list(SETTINGS))
    parser.add_argument("--table", type=Path, default=TABLE)
    args = parser.parse_args(argv)
    setting = SETTINGS[args.setting]
    code = commit_of(ROOT)
    rows = read_table(args.table)
    single = profile(args.preset, args.steps, args.warmup, [])["step_ms"]["unprofiled"]
    print(f"single scene: {single:.1f} ms a step", flush=True)
    for k in map(int, args.members.split(",")):
        todo = pending(rows, args.preset, k, args.per_step.split(","), args.setting)
        if not todo:
            continue
        run, _ = train("ea", output_dir(), args.preset,
                       [*family_overrides(k), *setting, f"budget.ea.steps={args.ea_steps}",
                        f"budget.val_every={args.ea_steps}"])
        for m in todo:
            per_step = "null" if m == "all" else m
            report = profile(args.preset, args.steps, args.warmup,
                             [*family_overrides(k), *setting,
                              f"data.members_per_step={per_step}"],
                             run / LAST_CKPT)
            ms = report["step_ms"]["unprofiled"]
            row = {"preset": args.preset, "setting": args.setting, "members": k,
                   "per_step": m, "step_ms": f"{ms:.1f}",
                   "single_scene_ms": f"{single:.1f}", "ratio": f"{ms / single:.2f}",
                   "refreshes": report["uncollided_refreshes"]["count"],
                   "largest": largest(report), "code": code}
            rows.append(row)
            args.table.parent.mkdir(parents=True, exist_ok=True)
            with open(args.table, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=FIELDS)
                writer.writeheader()
                writer.writerows(rows)
            print(f"{args.setting}, K = {k}, M = {m}: {ms:.1f} ms a step, "
                  f"{ms / single:.2f}x the single scene ({largest(report)})", flush=True)
    return rows


if __name__ == "__main__":
    main()
