"""Stage 2 is deterministic for a given EA checkpoint, and its result is pinned: a change
that moves ``medium_grids.npz`` by one bit fails here, and the pin is regenerated only by a
deliberate change of what stage 2 computes.

The run: ``nrt-train stage=rte preset=tiny`` for :data:`STEPS` steps (validation, the
uncollided light's refreshes and the medium's two upsamplings included) from a fixed EA
checkpoint made in the test (an untrained tiny EA field under ``torch.manual_seed(0)``), on
the session's tiny dataset. Its digest is the SHA-256 of every array of the export (name,
dtype, shape, bytes; not the zip file, whose metadata carry times).

The digest is machine dependent: the dataset is rendered by Mitsuba's LLVM backend, which
compiles for the CPU it runs on, and stage 2 runs torch's CPU kernels, whose vector width
(the CPU's capability) and MKL's matrix products, which pick their kernels by the CPU's
vendor and instruction sets, change rounding. So the pin is keyed by a fingerprint of what
decides the bits: torch's version and CPU capability, the CPU itself (vendor, family, model
and flags, from ``/proc/cpuinfo``) and the dataset's bytes. Two machines with the same
torch capability and the same dataset bytes were seen to end at different digests, so the
capability alone does not decide them. Where the fingerprint is pinned, one run
must give the pin's digest (repeating the pin's bits, it is also deterministic). On a
machine with an unpinned fingerprint the run is repeated and both digests must agree
(determinism), and the pin check is skipped, naming the digest and fingerprint to pin.
"""

from __future__ import annotations

import hashlib
import platform
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.conftest import only_run_dir, run_train, single_scene_ea_checkpoint

pytestmark = pytest.mark.e2e

STEPS = 120
OVERRIDES = (f"budget.rte.steps={STEPS}", "budget.val_every=60",
             "budget.checkpoint_every=60", "logger=tensorboard", "threads=2")
"""Two torch threads whatever the machine: a grid's gradient is summed over one lookup batch
per thread (nrt.physics.volume.lookup_batches), so the thread count decides its rounding."""

PINNED = {  # fingerprint -> digest of medium_grids.npz
    # AMD EPYC, family 25 model 1 (AVX2), torch 2.14.1: two runs, the same bits
    "6bfafe043595cb24": "c73486df2354fa737dd9a586579fde6f51f16af047af08e9a3736068287900e3",
    # AMD EPYC, family 25 model 17 (AVX-512), torch 2.14.1: two runs, the same bits
    "d121a9b013a76ff3": "6e14bb2a6dd4a700af54cdd82edd71185680709726dab74aeefca7ec87ecfe58",
}


def array_digest(path: Path) -> str:
    """SHA-256 over the arrays of an ``.npz`` file, in name order: name, dtype, shape, bytes."""
    h = hashlib.sha256()
    with np.load(path) as arrays:
        for name in sorted(arrays.files):
            a = np.ascontiguousarray(arrays[name])
            h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode())
            h.update(a.tobytes())
    return h.hexdigest()


def cpu_identity() -> str:
    """The CPU's vendor, family, model, stepping and flags (the first processor of
    ``/proc/cpuinfo``), else ``platform``'s machine and processor names."""
    try:
        first = Path("/proc/cpuinfo").read_text().split("\n\n")[0]
    except OSError:
        return f"{platform.machine()}|{platform.processor()}"
    fields = dict(line.split(":", 1) for line in first.splitlines() if ":" in line)
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    keys = ("vendor_id", "cpu family", "model", "stepping", "flags")
    return "|".join(fields.get(k, "") for k in keys)


def fingerprint(dataset: Path) -> str:
    """What decides the digest's bits besides nrt: torch's version and CPU capability, the
    CPU (:func:`cpu_identity`), and the dataset's files (their bytes, in path order)."""
    h = hashlib.sha256()
    h.update(f"{torch.__version__}|{torch.backends.cpu.get_cpu_capability()}".encode())
    h.update(cpu_identity().encode())
    for path in sorted(p for p in dataset.rglob("*") if p.is_file() and p.name != "scene.json"):
        h.update(str(path.relative_to(dataset)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def stage_2_digest(out: Path, data_root: Path, ea_ckpt: Path) -> str:
    """The digest of ``medium_grids.npz`` of one stage-2 run from ``ea_ckpt``."""
    proc = run_train(out, data_root, f"init.ea_ckpt={ea_ckpt}", *OVERRIDES, stage="rte")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return array_digest(only_run_dir(out, "rte") / "medium_grids.npz")


@pytest.mark.slow
def test_stage_2_from_a_fixed_ea_checkpoint_is_deterministic_and_pinned(tmp_path, tiny_dataset):
    """Where the fingerprint is pinned, one run matching the pin proves both properties (a
    run that repeats the pin's bits is repeatable); elsewhere two runs must agree."""
    torch.manual_seed(0)
    ea_ckpt = single_scene_ea_checkpoint(tmp_path / "ea.ckpt")
    digest = stage_2_digest(tmp_path / "run0", tiny_dataset.parent, ea_ckpt)
    key = fingerprint(tiny_dataset)
    if key in PINNED:
        assert digest == PINNED[key], (
            f"stage 2's export changed on machine {key!r} (digest {digest!r}); pin the new "
            "digest only if the change is deliberate")
        return
    again = stage_2_digest(tmp_path / "run1", tiny_dataset.parent, ea_ckpt)
    assert digest == again, "stage 2 is not deterministic for a fixed checkpoint"
    pytest.skip(f"no pinned digest for this machine: PINNED[{key!r}] = {digest!r}")
