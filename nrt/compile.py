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

The same compiler builds nrt's own C++ extensions (:func:`load_extension`; the fused CPU
hash grid, ``hash_grid.fused``) at first use, cached per machine under
:func:`extensions_dir`.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

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


EXTENSIONS_DIR_ENV = "NRT_EXTENSIONS_DIR"


def extensions_dir() -> Path:
    """``$NRT_EXTENSIONS_DIR``, else ``$XDG_CACHE_HOME/nrt/extensions``
    (``~/.cache/nrt/extensions``): where :func:`load_extension` builds."""
    if os.environ.get(EXTENSIONS_DIR_ENV):
        return Path(os.environ[EXTENSIONS_DIR_ENV]).expanduser()
    cache = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(cache).expanduser() / "nrt" / "extensions"


def load_extension(name: str, sources: Sequence[Path]) -> ModuleType:
    """The C++ extension ``name`` built from ``sources`` with ``torch.utils.cpp_extension``
    (``-O3`` without fused multiply-adds, and OpenMP where ATen's thread pool is OpenMP's, so
    that ``at::parallel_for`` runs on ``torch.get_num_threads()`` threads) and imported. The
    build goes to ``extensions_dir()/<name>/<python>_torch<version>`` and is reused until a
    source or a flag changes. Raises RuntimeError saying why where it cannot be built."""
    missing = missing_compiler("cpu")
    if missing:
        raise RuntimeError(missing)
    import torch

    quiet = logging.getLogger("torch.utils.cpp_extension")  # its import warns without CUDA
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        from torch.utils import cpp_extension
    finally:
        quiet.setLevel(level)

    if not cpp_extension.is_ninja_available():
        raise RuntimeError("torch builds C++ extensions with ninja, which is not installed "
                           "(pip install ninja)")
    flags = ["-O3", "-ffp-contract=off"]  # no fused multiply-adds: PyTorch's rounding
    if torch.backends.openmp.is_available() and sys.platform != "win32":
        flags.append("-fopenmp")
    version = f"py{sys.version_info.major}{sys.version_info.minor}_torch{torch.__version__}"
    build = extensions_dir() / name / version.replace("+", "_")
    build.mkdir(parents=True, exist_ok=True)
    try:
        return cpp_extension.load(name, [str(s) for s in sources], extra_cflags=flags,
                                  extra_ldflags=flags[2:], build_directory=str(build))
    except Exception as e:  # a compiler error, missing headers: say which, in a line
        lines = str(e).strip().splitlines() or [repr(e)]
        why = next((line for line in lines if "error:" in line), lines[0])
        raise RuntimeError(f"building {name} in {build} failed: {why.strip()[:300]}") from e


class LazyExtension:
    """A C++ extension built at first use (:func:`load_extension`) by whoever asks for it
    first, or the reason it cannot be built: :meth:`get` warns once per process, naming
    ``what`` uses it and that ``fallback`` runs instead."""

    def __init__(self, name: str, sources: Sequence[Path], what: str, logger: logging.Logger):
        self.name, self.sources, self.what, self.log = name, tuple(sources), what, logger
        self._module: ModuleType | None = None
        self._why: str | None = None

    def get(self) -> ModuleType | None:
        """The built extension, or None where it cannot be built (:meth:`unavailable`)."""
        if self._module is None and self._why is None:
            try:
                self._module = load_extension(self.name, self.sources)
            except RuntimeError as e:
                self.log.warning("%s is unavailable (%s); using the PyTorch path.", self.what, e)
                self._why = str(e)
        return self._module

    def unavailable(self) -> str | None:
        """Why :meth:`get` could not build the extension; None where it could (or has not
        tried yet)."""
        return self._why

