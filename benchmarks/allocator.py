"""Effect of nrt's glibc malloc tuning on a training step, measured side by side.

Runs the same EA training step loop in fresh subprocesses, alternately with glibc's
default allocator settings (``NRT_KEEP_MALLOC=1``) and with nrt's ``tune_allocator()``,
and prints the median step time of each and their ratio.

    python benchmarks/allocator.py [--rays 8192] [--samples 64] [--steps 15] [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys

_CHILD = r"""
import sys, time, torch
from nrt.cli.common import tune_allocator
from nrt.modules.fields.ea_field import EAField
from nrt.modules.renderers.emission_absorption import render_rays
tuned = tune_allocator()
rays, samples, steps = (int(a) for a in sys.argv[1:4])
torch.manual_seed(0)
field = EAField(hash_grid={"levels": 12, "log2_table_size": 17})
opt = torch.optim.Adam(field.parameters(), 1e-2)
o = torch.randn(rays, 3); o = 4.5 * o / o.norm(dim=-1, keepdim=True)
d = -o / 4.5 + 0.1 * torch.randn(rays, 3); d = d / d.norm(dim=-1, keepdim=True)
bg = torch.rand(rays, 3)
times = []
for i in range(steps + 2):
    t = time.perf_counter()
    loss = render_rays(field, o, d, bg, samples, jitter=True).square().mean()
    opt.zero_grad(); loss.backward(); opt.step()
    times.append(time.perf_counter() - t)
print(tuned, *times[2:])
"""


def run(tuned: bool, rays: int, samples: int, steps: int) -> list[float]:
    env = dict(os.environ)
    env.pop("NRT_KEEP_MALLOC", None)
    if not tuned:
        env["NRT_KEEP_MALLOC"] = "1"
    out = subprocess.run([sys.executable, "-c", _CHILD, str(rays), str(samples), str(steps)],
                         env=env, capture_output=True, text=True, check=True).stdout.split()
    return [float(x) for x in out[1:]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=8192)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--steps", type=int, default=15)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    default, tuned = [], []
    for _ in range(args.rounds):  # alternate, so drifts in machine load hit both alike
        default += run(False, args.rays, args.samples, args.steps)
        tuned += run(True, args.rays, args.samples, args.steps)
    d, t = statistics.median(default), statistics.median(tuned)
    print(f"EA step, {args.rays} rays x {args.samples} samples, median of "
          f"{len(default)} steps each:")
    print(f"  glibc defaults : {d * 1e3:8.1f} ms/step")
    print(f"  tune_allocator : {t * 1e3:8.1f} ms/step   (speed-up x{d / t:.2f})")


if __name__ == "__main__":
    main()
