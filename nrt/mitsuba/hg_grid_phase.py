"""``nrt_hg_grid``: a Mitsuba phase plugin, Henyey-Greenstein with ``g`` read from a volume.

The plugin takes one nested volume ``g`` (a ``gridvolume`` in world space, or ``constvolume``)
and evaluates HG(g(x)) at each scattering point. Mitsuba's ``mi.wi`` points back along the
incoming path, so the cosine between travel directions is ``-dot(wi, wo)`` (nrt.physics.phase
convention). ``g`` is clamped to |g| <= 0.95 and, for |g| < 1e-2, the inversion sampler
uses the second-order Taylor series of the HG inversion in g, as
:func:`nrt.physics.phase.sample_hg_cos` does (so the sampled density is HG to 1e-6 and the
returned weight 1 and pdf ``hg(cos, g)`` stay consistent).
"""

from __future__ import annotations

import math


def make_hg_grid_phase(mi):
    """The plugin class for the active Mitsuba variant (Dr.Jit types differ per variant)."""
    import drjit as dr

    inv_4pi = 1.0 / (4 * math.pi)

    def hg(cos, g):
        denom = dr.maximum(1 + g * g - 2 * g * cos, 1e-12)
        return (1 - g * g) * inv_4pi / (denom * dr.sqrt(denom))

    class HGGridPhase(mi.PhaseFunction):
        def __init__(self, props):
            mi.PhaseFunction.__init__(self, props)
            self.g = props["g"]
            self.m_flags = mi.PhaseFunctionFlags.Anisotropic

        def _g(self, mei, active):
            return dr.clip(self.g.eval_1(mei, active), -0.95, 0.95)

        def sample(self, ctx, mei, sample1, sample2, active=True):
            g = self._g(mei, active)
            small = dr.abs(g) < 1e-2
            g_safe = dr.select(small, 1e-2, g)
            s = (1 - g_safe * g_safe) / (1 - g_safe + 2 * g_safe * sample2.x)
            a = 2 * sample2.x - 1
            cos = dr.select(small, a + g * (1 - a * a) * (1.5 - 2 * g * a),
                            (1 + g_safe * g_safe - s * s) / (2 * g_safe))
            cos = dr.clip(cos, -1.0, 1.0)
            sin = dr.safe_sqrt(1 - cos * cos)
            sin_phi, cos_phi = dr.sincos(2 * math.pi * sample2.y)
            local = mi.Vector3f(sin * cos_phi, sin * sin_phi, cos)
            wo = mi.Frame3f(-mei.wi).to_world(local)
            pdf = hg(cos, g)
            return wo, mi.Spectrum(1.0), pdf

        def eval_pdf(self, ctx, mei, wo, active=True):
            pdf = hg(-dr.dot(mei.wi, wo), self._g(mei, active))
            return mi.Spectrum(pdf), pdf

        def traverse(self, callback):
            callback.put("g", self.g, mi.ParamFlags.NonDifferentiable)

        def to_string(self):
            return f"HGGridPhase[g={self.g}]"

    return HGGridPhase
