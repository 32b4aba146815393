"""The Gaussian fitted to a generative run's learned latent codes, and samples from it.

An auto-decoder (DeepSDF manner) learns one code z_k per training scene; new media are
decoded from codes drawn from ``N(mu, Sigma)`` fitted to them: ``mu`` the codes' mean and
``Sigma`` their unbiased sample covariance (divisor K - 1).

Guard for few codes: K codes span at most K - 1 directions, so for ``K <= d_z`` the sample
covariance ``S`` is singular and a Gaussian with it draws only inside the codes' affine span
(with ``K = 2``: on the line through both codes). The fit then shrinks ``S`` toward its
diagonal, ``Sigma = (1 - lam) S + lam diag(S)``, which keeps every code dimension's variance
and makes ``Sigma`` positive definite whenever every dimension varies. ``lam`` ("auto") is 0
for ``K > d_z`` (the plain full covariance) and ``(d_z - K + 1) / d_z`` for ``K <= d_z``:
the share of dimensions that ``S`` misses (its rank deficit over d_z), so one code short of
full rank shrinks by 1/d_z and K = 1 would shrink fully. A number in [0, 1] overrides it.
A dimension along which no two codes differ keeps variance 0 (its samples equal the mean).

Two ways to draw (``sample``): from the Gaussian itself, its spread about the mean scaled by a
``temperature`` (1: the fit; below 1 the draws keep closer to the mean, the "truncation" of
generative models), or, with a ``bandwidth`` h, a smoothed bootstrap of the codes (Silverman
1986, section 6.4): take a learned code, add Gaussian noise of covariance ``h^2 Sigma`` and
shrink the sum toward the mean by ``1 / sqrt(1 + h^2)``, so that the draws keep the codes'
mean and, up to the divisor (K against K - 1), their covariance. The codes are taken in turn,
each round of K draws in a random order of all K, so that K draws start once from every
code, as FID's reference takes the true media in turn. h -> 0 gives back the learned codes
themselves, h -> infinity the Gaussian; in between, the draws stay near the codes the
decoder was trained on without repeating them. Scott's rule for a kernel estimate of K
points in d_z dimensions is h = K^(-1 / (d_z + 4)) (0.87 for K = d_z = 16).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from nrt.errors import ConfigError


def auto_shrinkage(count: int, dim: int) -> float:
    """``lam`` of the module docstring: 0 for K > d_z, else (d_z - K + 1) / d_z."""
    return 0.0 if count > dim else (dim - count + 1) / dim


@dataclass(frozen=True)
class LatentGaussian:
    """``N(mean, cov)`` over codes of ``dim`` values, fitted to the ``codes`` (count, dim)
    with covariance shrinkage ``shrinkage`` (float64 tensors on the CPU)."""

    mean: torch.Tensor
    cov: torch.Tensor
    shrinkage: float
    codes: torch.Tensor

    @property
    def count(self) -> int:
        return int(self.codes.shape[0])

    @property
    def dim(self) -> int:
        return int(self.mean.shape[0])

    def factor(self) -> torch.Tensor:
        """A square root ``A`` of ``cov`` (``A A^T = cov``), from its eigendecomposition
        (exact for the positive semi-definite covariances of few codes, unlike Cholesky)."""
        evals, evecs = torch.linalg.eigh(self.cov)
        return evecs * evals.clamp_min(0).sqrt()

    def sample(self, n: int, seed: int = 0, temperature: float = 1.0,
               bandwidth: float | None = None) -> torch.Tensor:
        """``n`` codes (n, dim), float32, drawn with a generator seeded by ``seed``: from the
        Gaussian with its spread scaled by ``temperature``, or, with ``bandwidth`` h, the
        smoothed bootstrap of the fitted codes (module docstring; ``temperature`` is then
        not read)."""
        gen = torch.Generator().manual_seed(int(seed))
        if bandwidth is None:
            eps = torch.randn(int(n), self.dim, generator=gen, dtype=torch.float64)
            return (self.mean + float(temperature) * eps @ self.factor().T).float()
        rounds = -(-int(n) // self.count)
        pick = torch.cat([torch.randperm(self.count, generator=gen)
                          for _ in range(rounds)])[:int(n)]
        return self.around(pick, float(bandwidth), gen)

    def around(self, members: torch.Tensor, bandwidth: float,
               generator: torch.Generator) -> torch.Tensor:
        """One smoothed-bootstrap draw at ``bandwidth`` h around each code of ``members``
        (M,) (indices into ``codes``), (M, dim) float32: the code plus Gaussian noise of
        covariance ``h^2 Sigma``, shrunk toward the mean by ``1 / sqrt(1 + h^2)``."""
        eps = torch.randn(len(members), self.dim, generator=generator, dtype=torch.float64)
        h = float(bandwidth)
        centred = self.codes[members] - self.mean
        return (self.mean + (centred + h * eps @ self.factor().T) / math.sqrt(1 + h * h)
                ).float()


def fit_latent_gaussian(codes: torch.Tensor, shrinkage: float | str = "auto") -> LatentGaussian:
    """Fit ``N(mu, Sigma)`` to ``codes`` (K, d_z), K >= 2 (module docstring)."""
    codes = torch.as_tensor(codes).detach().double().cpu()
    if codes.ndim != 2 or codes.shape[0] < 2:
        raise ConfigError(f"A Gaussian over latent codes needs at least 2 codes of shape "
                          f"(K, d_z); got {tuple(codes.shape)}. Train the generative run on "
                          "a family of K >= 2 members (scene.family.members).")
    if not torch.isfinite(codes).all():
        raise ConfigError("The run's latent codes are not all finite: its training diverged; "
                          "retrain it (or resume from an earlier checkpoint).")
    count, dim = codes.shape
    if shrinkage == "auto":
        lam = auto_shrinkage(count, dim)
    elif isinstance(shrinkage, (int, float)) and not isinstance(shrinkage, bool) \
            and 0.0 <= float(shrinkage) <= 1.0:
        lam = float(shrinkage)
    else:
        raise ConfigError(f"gaussian.shrinkage={shrinkage!r}: give auto or a number in "
                          "[0, 1] (0: the full sample covariance, 1: its diagonal only).")
    mean = codes.mean(0)
    centred = codes - mean
    sample_cov = centred.T @ centred / (count - 1)
    cov = (1 - lam) * sample_cov + lam * torch.diag(torch.diagonal(sample_cov))
    return LatentGaussian(mean=mean, cov=cov, shrinkage=lam, codes=codes)


def scott_bandwidth(count: int, dim: int) -> float:
    """Scott's rule for a Gaussian kernel estimate of ``count`` points in ``dim``
    dimensions, in units of their covariance: ``count ** (-1 / (dim + 4))``."""
    return float(count) ** (-1.0 / (dim + 4))
