"""``compile=true``: a stage's hot code compiled by ``torch.compile`` (inductor: its C++
backend on the CPU, Triton on CUDA), with an eager fallback where no compiler is present.

What a stage compiles is its own choice (:meth:`nrt.stages.stage.Stage.compile_hot_code`):
stage 1 compiles its hash-grid field (1.23x the steps per second at ``cpu`` on 2 cores,
benchmarks/README.md); stage 2 compiles nothing (its uncollided-light refresh, compiled,
spent minutes compiling and recompiling at ``cpu``: 12.8 s a step against 0.51 eager).
Compiled code fuses chains of element-wise ops, so it computes the same quantities with
other float rounding: a run is reproducible per setting, not bit-identical across the two
settings. Compiling costs tens of seconds in the first step (counted in the run's training
seconds); inductor's kernels are cached under ``cache_dir`` (by default
``<paths.output_dir>/.cache/inductor``), so a second run of the same code compiles in
seconds.
"""

from __future__ import annotations

import importlib.util
import os
import shutil

CXX_CANDIDATES = ("g++", "c++", "clang++")


def missing_compiler(device_type: str) -> str | None:
    """Why ``torch.compile`` cannot build kernels for ``device_type`` here (``cpu``: no C++
    compiler on the PATH or in ``CXX``; ``cuda``: no Triton), or None when it can."""
    if device_type == "cuda":
        return None if importlib.util.find_spec("triton") else "Triton is not installed"
    names = [os.environ["CXX"]] if os.environ.get("CXX") else list(CXX_CANDIDATES)
    if any(shutil.which(name) for name in names):
        return None
    return f"no C++ compiler found ({', '.join(names)}; set CXX or install g++)"


def use_cache(cache_dir: str | None) -> None:
    """Keep inductor's kernels under ``cache_dir`` (unless ``TORCHINDUCTOR_CACHE_DIR`` is
    set already, or ``cache_dir`` is None)."""
    if cache_dir and "TORCHINDUCTOR_CACHE_DIR" not in os.environ:
        os.makedirs(cache_dir, exist_ok=True)
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = os.path.abspath(cache_dir)
