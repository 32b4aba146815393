"""Emission-absorption field: density and colour from a hash grid and two small MLPs.

Stage 1 of nrt (the paper's EA NeRF): its colour is discarded and its density
``rho_EA(x)`` (per unit length, world units) seeds the medium of stage 2, which queries
it through :meth:`EAField.density`. Points are world coordinates inside ``bbox``.

A field built with ``latent_dim > 0`` is conditioned on a latent code z (the generative
auto-decoder, ``mode=generative``): the hash-grid features are multiplied channel by channel
by ``1 + M(z)``, ``M`` a small MLP (its output layer starts at zero, so every code starts
from the same field); with ``latent_input`` the density MLP also reads z beside the
features (DeepSDF's conditioning; z's input weights start at zero, for the same reason).
Such a field needs a code at every query; one without
(``latent_dim = 0``, the default) refuses one and builds exactly the parameters it always
had, in the same order, so single-scene runs draw the same random numbers.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.profiler import record_function

from nrt.errors import ConfigError
from nrt.modules.encodings.activations import DENSITY_ACTIVATIONS
from nrt.modules.encodings.hash_grid import HashGrid
from nrt.physics.sh import condon_shortley_signs, num_coefficients, sh_basis

SH_DEGREE = 2
"""The colour's view directions enter as real SH up to degree 2 (9 values)."""


def mlp(n_in: int, hidden: int, n_out: int, layers: int) -> nn.Sequential:
    """``layers`` hidden ReLU layers of width ``hidden`` and a linear output."""
    dims = [n_in] + [hidden] * layers
    mods: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:], strict=True):
        mods += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*mods, nn.Linear(dims[-1], n_out))


class EAField(nn.Module):
    """``(x, w) -> (sigma, rgb)``: density per unit length (>= 0) and HDR colour (>= 0)."""

    def __init__(self, hash_grid: dict | None = None, hidden: int = 64, layers: int = 1,
                 geo_features: int = 15, density_activation: str = "trunc_exp",
                 density_bias: float = -1.0, latent_dim: int = 0, modulation_hidden: int = 32,
                 latent_input: bool = False):
        super().__init__()
        if density_activation not in DENSITY_ACTIVATIONS:
            raise ConfigError(f"model.density_field.density_activation must be one of "
                              f"{sorted(DENSITY_ACTIVATIONS)}, got '{density_activation}'.")
        if latent_input and latent_dim <= 0:
            raise ConfigError("model.density_field.latent_input=true feeds the latent code to "
                              "the density MLP: it needs latent_dim > 0 (mode=generative).")
        self.latent_input = bool(latent_input)
        self.encoding = HashGrid(**(hash_grid or {}))
        n_in = self.encoding.output_dim + (int(latent_dim) if self.latent_input else 0)
        self.density_net = mlp(n_in, hidden, 1 + geo_features, layers)
        if self.latent_input:
            with torch.no_grad():
                self.density_net[0].weight[:, self.encoding.output_dim:] = 0.0
        self.color_net = mlp(geo_features + num_coefficients(SH_DEGREE), hidden, 3, layers)
        self.activation = DENSITY_ACTIVATIONS[density_activation]
        self.density_bias = density_bias
        self.register_buffer("bbox", torch.tensor([[-1.0] * 3, [1.0] * 3]))
        # The colour net reads SH up to degree 2 without the Condon-Shortley phase (the
        # table it was written with): trained weights depend on these signs.
        self.register_buffer("sh_signs", condon_shortley_signs(SH_DEGREE), persistent=False)
        self.latent_dim = int(latent_dim)
        self.modulation: nn.Sequential | None = None
        if self.latent_dim > 0:  # built last: the unconditioned parameters draw as before
            self.modulation = mlp(self.latent_dim, modulation_hidden, self.encoding.output_dim, 1)
            nn.init.zeros_(self.modulation[-1].weight)
            nn.init.zeros_(self.modulation[-1].bias)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """The hash-grid features (..., levels * features) at world points ``x`` (..., 3)."""
        return self.encoding((x - self.bbox[0]) / (self.bbox[1] - self.bbox[0]))

    def _features(self, encoded: torch.Tensor, latent: torch.Tensor | None) -> torch.Tensor:
        if self.modulation is not None:
            if latent is None or latent.shape[-1] != self.latent_dim:
                raise ValueError(f"this EA field is conditioned on latent codes of dimension "
                                 f"{self.latent_dim}: pass latent (..., {self.latent_dim}) "
                                 "broadcastable against the points' leading dimensions.")
            encoded = encoded * (1.0 + self.modulation(latent))
            if self.latent_input:
                code = latent.to(encoded).expand(*encoded.shape[:-1], self.latent_dim)
                encoded = torch.cat((encoded, code), -1)
        elif latent is not None:
            raise ValueError("this EA field has no latent code (latent_dim=0); build it with "
                             "latent_dim > 0 to condition it on one.")
        with record_function("nrt/mlp"):  # profiler scopes (benchmarks.profile_step)
            return self.density_net(encoded)

    def density_of_encoding(self, encoded: torch.Tensor, latent: torch.Tensor | None = None
                            ) -> torch.Tensor:
        """:meth:`density` from features :meth:`encode` gave (a frozen field's features at
        fixed points can be computed once; ``latent`` as in :meth:`density`)."""
        return self.activation(self._features(encoded, latent)[..., 0] + self.density_bias)

    def density(self, x: torch.Tensor, latent: torch.Tensor | None = None) -> torch.Tensor:
        """Density ``rho_EA`` (...,) at world points ``x`` (..., 3); stage 2 calls this.
        ``latent`` (..., d_z), broadcastable against ``x``'s leading dimensions, is required
        exactly when the field is conditioned (``latent_dim > 0``)."""
        with record_function("nrt/density_field"):
            return self.density_of_encoding(self.encode(x), latent)

    def forward(self, x: torch.Tensor, d: torch.Tensor, latent: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Density (...,) and colour (..., 3) at points ``x`` seen along view directions ``d``
        (``latent`` as in :meth:`density`)."""
        with record_function("nrt/density_field"):
            h = self._features(self.encode(x), latent)
            sigma = self.activation(h[..., 0] + self.density_bias)
            view = sh_basis(d, SH_DEGREE) * self.sh_signs.to(d.dtype)
            features = torch.cat((h[..., 1:], view), -1)
            with record_function("nrt/mlp"):
                colour = self.color_net(features)
            return sigma, nn.functional.softplus(colour)
