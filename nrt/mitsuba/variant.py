"""Mitsuba's variant for nrt: the fastest RGB variant that renders here, chosen once.

Choosing a variant also registers nrt's plugins (``nrt_hg_grid``,
:mod:`nrt.mitsuba.hg_grid_phase`), so every scene built after :func:`select_variant` may
name them.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys

from nrt.errors import NrtError
from nrt.mitsuba.hg_grid_phase import make_hg_grid_phase

log = logging.getLogger(__name__)

_PROBE = (
    "import mitsuba as mi; mi.set_variant('{v}'); "
    "s = mi.load_dict({{'type': 'scene', 'integrator': {{'type': 'path'}}, "
    "'shape': {{'type': 'sphere'}}, "
    "'sensor': {{'type': 'perspective', "
    "'film': {{'type': 'hdrfilm', 'width': 4, 'height': 4}}}}}}); "
    "mi.render(s, spp=1)"
)
_chosen_variant: str | None = None


def _variant_works(variant: str) -> bool:
    """Render a 4x4 image with ``variant`` in a subprocess (a bad LLVM aborts the process)."""
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE.format(v=variant)],
                              capture_output=True, timeout=300)
    except subprocess.TimeoutExpired:
        return False
    return proc.returncode == 0


def _cuda_present() -> bool:
    try:
        import torch

        return torch.cuda.is_available()
    except Exception:  # torch without CUDA support, or no driver
        return False


def select_variant(preferred: str = "auto"):
    """Set and return the Mitsuba module on the fastest working RGB variant.

    ``preferred='auto'`` tries ``cuda_ad_rgb`` (when CUDA is present), then ``llvm_ad_rgb``
    (needs LLVM >= 16, e.g. ``apt-get install libllvm19``), then ``scalar_rgb``; the
    environment variable ``NRT_MITSUBA_VARIANT`` overrides it. The choice is logged.
    """
    global _chosen_variant
    import mitsuba as mi

    preferred = os.environ.get("NRT_MITSUBA_VARIANT", preferred)
    if _chosen_variant is None:
        if preferred != "auto":
            if preferred not in mi.variants():
                raise NrtError(f"Mitsuba variant '{preferred}' (render.variant or "
                               f"NRT_MITSUBA_VARIANT) is not one of {mi.variants()}.")
            candidates = [preferred]
        else:
            candidates = (["cuda_ad_rgb"] if _cuda_present() else []) + ["llvm_ad_rgb"]
        _chosen_variant = next((v for v in candidates if _variant_works(v)), None)
        if _chosen_variant is None:
            if preferred != "auto":
                raise NrtError(f"Mitsuba variant '{preferred}' fails to render here. For "
                               "llvm_ad_rgb install a newer LLVM (apt-get install libllvm19) "
                               "or set DRJIT_LIBLLVM_PATH; or use render.variant=auto.")
            log.warning("llvm_ad_rgb does not work here (LLVM >= 16 missing: apt-get install "
                        "libllvm19); falling back to the slow scalar_rgb variant.")
            _chosen_variant = "scalar_rgb"
        log.info("Mitsuba %s, variant %s", mi.__version__, _chosen_variant)
    mi.set_variant(_chosen_variant)
    _register_plugins(mi)
    return mi


def _register_plugins(mi) -> None:
    mi.register_phase("nrt_hg_grid", make_hg_grid_phase(mi))
