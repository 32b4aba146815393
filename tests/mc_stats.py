"""Monte Carlo statistics for comparing Mitsuba renders with deterministic references.

The two-seed method: render the same scene twice with independent seeds, ``A`` and ``B``.
Each pixel of ``A`` is ``mu + e_A``, with ``e_A`` zero-mean noise of variance ``s^2``
(varying from pixel to pixel), independent of ``e_B`` and of the other pixels (Mitsuba's
``independent`` sampler draws every pixel's samples afresh). Hence

- ``E[(A - B)^2] = 2 s^2``: the pooled single-render noise variance of a region is
  ``mean((A - B)^2) / 2``, and that of ``M = (A + B) / 2`` is half of it;
- the region mean of ``M`` has standard error ``SE = sqrt(var_M / N)`` for ``N`` pixels,
  so ``|mean(M) - mean(ref)| < 5 SE`` fails by chance with probability < 1e-6 (normal
  tail; the mean of hundreds of pixels is close to normal even when single pixels are
  heavy-tailed);
- ``E[mean((M - ref)^2)] = var_M`` exactly when ``ref`` is right: the *structure ratio*
  ``mean((M - ref)^2) / var_M`` is ~1. For Gaussian noise ``A + B`` and ``A - B`` are
  independent and the ratio is F(N, N)-distributed: ``log(ratio)`` has standard deviation
  ``~sqrt(4/N)`` (numerator and pooled denominator each have chi-square spread
  ``sqrt(2/N)``), 0.06-0.1 for 400-1000 pixels. Where the noise variance differs between
  pixels (a box edge, a bright patch), fewer pixels carry the sums: ``N`` is replaced by
  the effective count ``n_eff = (sum s_i^2)^2 / sum s_i^4``, estimated from the squared
  differences ``q_i = (A_i - B_i)^2`` as ``3 (sum q)^2 / sum q^2`` (``E[q^2] = 3 E[q]^2``
  for Gaussian noise; heavier tails make the estimate smaller, i.e. the bound looser; it
  is computed from ``A - B`` alone, so a wrong reference cannot loosen it). The bound
  ``exp(5 sqrt(4 / n_eff))`` (1.37 for 1024 equal pixels, 1.52 for 576) is then a 5-sigma
  one. A reference that is wrong by ``delta`` per pixel raises the ratio to
  ``1 + mean(delta^2)/var_M``, which catches misalignments (a pixel shift, a mirrored
  axis) whose errors cancel in the mean. Fireflies do not break it: a large
  outlier in ``A`` enters ``(A + B)^2`` and ``(A - B)^2`` alike.

``atol`` (absolute, in radiance units) covers float32 rounding where the noise can be ~0
(rays that see only a smooth sky); it is added to the standard error and, squared, to the
variance, so it only matters where the Monte Carlo noise is below it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nrt.cameras import Intrinsics, pixel_rays


@dataclass
class Comparison:
    """Per-channel statistics of ``M = (A + B) / 2`` against ``ref`` over a region."""

    n: int
    n_eff: float
    mean_m: np.ndarray
    mean_ref: np.ndarray
    se: np.ndarray
    z: np.ndarray
    ratio: np.ndarray
    atol: float

    def describe(self) -> str:
        return (f"N={self.n} n_eff={np.round(self.n_eff, 1)} mean(M)={np.round(self.mean_m, 5)} "
                f"mean(ref)={np.round(self.mean_ref, 5)} SE={self.se} z={np.round(self.z, 2)} "
                f"ratio={np.round(self.ratio, 3)}")

    def ratio_bound(self, sigmas: float = 5.0) -> np.ndarray:
        """``sigmas``-sigma upper bound of the structure ratio, per channel."""
        return np.exp(sigmas * np.sqrt(4 / self.n_eff))

    def assert_ok(self, z_max: float = 5.0, sigmas: float = 5.0, what: str = "") -> None:
        diff = np.abs(self.mean_m - self.mean_ref)
        assert np.all(diff < z_max * self.se + self.atol), (
            f"{what}: region mean differs by more than {z_max} SE: {self.describe()}")
        bound = self.ratio_bound(sigmas)
        assert np.all(self.ratio < bound), (
            f"{what}: per-pixel structure ratio above its bound {np.round(bound, 3)}: "
            f"{self.describe()}")


def effective_count(q: np.ndarray, moment_ratio: float = 3.0) -> np.ndarray:
    """``n_eff = k (sum q)^2 / sum q^2`` per channel of per-pixel squared differences ``q``
    (N, C), at most N (see the module docstring). ``k = E[q^2] / E[q]^2`` for Gaussian noise:
    3 for one squared difference, 2 for the sum of two of equal variance (the smaller value
    is the conservative one: it lowers n_eff and loosens the bound)."""
    q = np.asarray(q, np.float64)
    sq = np.maximum((q * q).sum(0), 1e-300)
    return np.minimum(moment_ratio * q.sum(0) ** 2 / sq, len(q))


def compare(a: np.ndarray, b: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None,
            atol: float = 0.0) -> Comparison:
    """Two-seed comparison of renders ``a``, ``b`` (H, W, C) with ``ref`` (H, W, C) over the
    pixels where ``mask`` (H, W) is true (all pixels by default)."""
    a, b, ref = (np.asarray(x, np.float64) for x in (a, b, ref))
    if mask is None:
        mask = np.ones(a.shape[:2], bool)
    a, b, ref = a[mask], b[mask], ref[mask]
    n = len(a)
    assert n >= 30, f"region too small for the statistics ({n} pixels)"
    m = (a + b) / 2
    var_m = np.mean((a - b) ** 2, 0) / 4 + atol**2  # (mean((A-B)^2) / 2) / 2
    se = np.sqrt(var_m / n)
    mean_m, mean_ref = m.mean(0), ref.mean(0)
    return Comparison(n=n, n_eff=effective_count((a - b) ** 2 + 4 * atol**2),
                      mean_m=mean_m, mean_ref=mean_ref, se=se, z=(mean_m - mean_ref) / se,
                      ratio=np.mean((m - ref) ** 2, 0) / var_m, atol=atol)


def compare_two(a1, b1, a2, b2, mask=None, atol: float = 0.0) -> Comparison:
    """Two-seed comparison of two estimators of the same expectation: ``M1 - M2`` against 0,
    with the noise variance of the difference ``var_M1 + var_M2``."""
    a1, b1, a2, b2 = (np.asarray(x, np.float64) for x in (a1, b1, a2, b2))
    if mask is None:
        mask = np.ones(a1.shape[:2], bool)
    a1, b1, a2, b2 = a1[mask], b1[mask], a2[mask], b2[mask]
    n = len(a1)
    assert n >= 30, f"region too small for the statistics ({n} pixels)"
    d = (a1 + b1) / 2 - (a2 + b2) / 2
    var_d = (np.mean((a1 - b1) ** 2, 0) + np.mean((a2 - b2) ** 2, 0)) / 4 + atol**2
    se = np.sqrt(var_d / n)
    mean_d = d.mean(0)
    q = (a1 - b1) ** 2 + (a2 - b2) ** 2 + 4 * atol**2  # each pixel's 4 var_d estimate
    return Comparison(n=n, n_eff=effective_count(q, 2.0), mean_m=mean_d,
                      mean_ref=np.zeros_like(mean_d), se=se, z=mean_d / se,
                      ratio=np.mean(d**2, 0) / var_d, atol=atol)


def footprint_average(fn, c2w: np.ndarray, intr: Intrinsics, n_sub: int,
                      chunk: int = 64) -> np.ndarray:
    """Average of ``fn(origins, dirs) -> (S, H, W, C)`` over an ``n_sub x n_sub`` stratified
    grid of rays inside every pixel (sub-cell centres; ``S <= chunk`` of them per call).

    Mitsuba's ``box`` filter averages uniformly jittered samples over the pixel, so a pixel's
    expected value is the area average of the radiance over the pixel; the midpoint rule
    reproduces it to O(n_sub^-2) where ``fn`` is smooth, and to O(1/n_sub) of a pixel's area
    where an edge crosses it.
    """
    c2w_t = torch.as_tensor(np.asarray(c2w), dtype=torch.float64)
    ij = (torch.arange(n_sub, dtype=torch.float64) + 0.5) / n_sub
    offsets = torch.stack(torch.meshgrid(ij, ij, indexing="ij"), -1).reshape(-1, 1, 1, 2)
    total = 0.0
    for start in range(0, len(offsets), chunk):
        o, d = pixel_rays(c2w_t, intr, offsets[start:start + chunk])
        total = total + fn(o, d).sum(0)
    return (total / n_sub**2).numpy()
