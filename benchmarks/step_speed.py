"""Training-step time of two settings side by side, in one run: by default the code as it
runs eagerly (``compile=false``) against ``compile=true`` (:mod:`nrt.compile`); with
``--a-code DIR`` setting A runs the nrt in ``DIR`` (a checkout of the code before a change,
e.g. ``git worktree add DIR <commit>``), so that a change is timed against its parent.

For each stage, :mod:`benchmarks.profile_step` runs once per setting and round, each in a
process of its own (compiled code and its caches stay in their process), the settings
alternating A B A B ... so that a drift of the machine's speed falls on both alike. Per
stage and setting: the mean and spread over rounds of the milliseconds per step in the
unprofiled window (after ``--warmup`` steps, the run's progress pinned at ``--at``), the
first step's seconds (where ``compile=true`` compiles; inductor's cache lives in
``<paths.output_dir>/.cache/inductor``, so a round after the first finds it warm, and the
first round's first step says what a cold cache costs), and the speed-up, B's steps per
second over A's. ``--json`` writes every round.

    python -m benchmarks.step_speed [--stages ea,rte] [--preset cpu] [--rounds 2]
        [--a compile=false] [--b compile=true] [--a-code DIR] [--b-code DIR] [--steps 20]
        [--warmup 5] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.common import commit_of

HERE = Path(__file__).resolve().parents[1]


def one_run(stage: str, preset: str, setting: list[str], steps: int, warmup: int,
            at: float, code: Path = HERE) -> dict:
    """One :mod:`benchmarks.profile_step` run of the nrt in ``code`` in its own process: its
    report. Outputs (datasets, EA checkpoints) are this tree's (``NRT_OUTPUT_DIR``)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "report.json"
        cmd = [sys.executable, "-m", "benchmarks.profile_step", "--stage", stage, "--preset",
               preset, "--steps", str(steps), "--warmup", str(warmup), "--at", str(at),
               "--probe-seconds", "0.2", "--json", str(out), *setting]
        env = {**os.environ, "PYTHONPATH": str(code),
               "NRT_OUTPUT_DIR": os.environ.get("NRT_OUTPUT_DIR", str(HERE / "outputs"))}
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=code, env=env)
        if done.returncode != 0:
            sys.exit(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
        return json.loads(out.read_text())


def summary(rows: list[dict], stages: list[str], names: tuple[str, str]) -> str:
    """The Markdown table of the rounds ``rows`` (stage, setting, ms, first_s)."""
    lines = ["| stage | setting | ms / step (mean +- sd over rounds) | first step s (rounds) "
             "| steps / s, B over A |", "| --- | --- | ---: | --- | ---: |"]
    for stage in stages:
        means = {}
        for name in names:
            mine = [r for r in rows if r["stage"] == stage and r["setting"] == name]
            ms = [r["ms"] for r in mine]
            means[name] = statistics.mean(ms)
            sd = statistics.stdev(ms) if len(ms) > 1 else float("nan")
            firsts = ", ".join(f"{r['first_s']:.1f}" for r in mine)
            ratio = f"{means[names[0]] / means[name]:.2f}x" if name == names[1] else ""
            lines.append(f"| {stage} | `{name}` | {means[name]:.1f} +- {sd:.1f} | {firsts} | "
                         f"{ratio} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stages", default="ea,rte")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--a", default="compile=false", help="setting A: overrides, spaces")
    parser.add_argument("--b", default="compile=true", help="setting B: overrides, spaces")
    parser.add_argument("--a-code", type=Path, default=HERE, help="the nrt setting A runs")
    parser.add_argument("--b-code", type=Path, default=HERE, help="the nrt setting B runs")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--at", type=float, default=0.5)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    stages = args.stages.split(",")
    codes = {"A": args.a_code.resolve(), "B": args.b_code.resolve()}
    names = tuple(f"{code}: {setting}" if codes["A"] != codes["B"] else setting
                  for code, setting in zip(("A", "B"), (args.a, args.b), strict=True))
    rows = []
    for stage in stages:
        for r in range(args.rounds):
            for name, setting, code in zip(names, (args.a, args.b), codes.values(),
                                           strict=True):
                report = one_run(stage, args.preset, setting.split(), args.steps, args.warmup,
                                 args.at, code)
                rows.append({"stage": stage, "setting": name, "round": r,
                             "ms": report["step_ms"]["unprofiled"],
                             "first_s": report.get("first_step_s", float("nan"))})
                print(f"{stage} {name} round {r}: {rows[-1]['ms']:.1f} ms/step, first step "
                      f"{rows[-1]['first_s']:.1f} s", flush=True)
    table = summary(rows, stages, names)
    print(table)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"preset": args.preset, "rounds": rows,
                                         "code": {k: commit_of(v) for k, v in codes.items()},
                                         "machine": report["machine"]}, indent=1))
    return table


if __name__ == "__main__":
    main()
