"""The voxel medium of split stage 2 composes the neural medium's heads on its cells and
interpolates between them."""

from __future__ import annotations

import pytest
import torch

from nrt.modules.fields.medium import NeuralMedium
from nrt.modules.fields.voxel_medium import LatentVoxelMedium, VoxelMedium
from nrt.physics.phase import G_MAX
from nrt.physics.volume import cell_centres

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("effects,parametrization", [
    ({"phase": "hg", "chromatic": True}, "scattering"),
    ({"phase": "hg", "chromatic": True}, "extinction"),
    ({"phase": "varying_hg", "chromatic": False}, "extinction"),
    ({"phase": "isotropic", "chromatic": True}, "extinction")])
def test_voxel_medium_composes_the_neural_heads_on_its_cells(effects, parametrization):
    """At the density's cell centres the composed voxels equal the heads of
    :class:`NeuralMedium` applied to the baked density and the (trilinearly upsampled)
    modulation; between them they interpolate linearly; grey media keep one sigma_t
    channel and an RGB albedo; g exists only for an HG phase."""
    torch.manual_seed(5)
    medium = VoxelMedium(effects, resolutions=[4], density_resolution=8,
                         parametrization=parametrization)
    medium.set_density(lambda p: 1 + p[:, 0] ** 2)
    start = medium(cell_centres(8, medium.bbox).reshape(-1, 3))  # sigma_t = rho, albedo 0.8
    torch.testing.assert_close(start.albedo, torch.full_like(start.albedo, 0.8))
    with torch.no_grad():
        medium.modulation.values.normal_(0, 0.3)
    centres = cell_centres(8, medium.bbox).reshape(-1, 3)
    ours, heads = medium(centres), NeuralMedium.forward(medium, centres)
    for key in ("sigma_a", "sigma_s", "albedo"):
        torch.testing.assert_close(getattr(ours, key), getattr(heads, key), rtol=1e-5,
                                   atol=1e-6)
    assert ours.sigma_t.shape[-1] == (3 if effects["chromatic"] else 1)
    assert (ours.g is None) == (effects["phase"] == "isotropic")
    mid = (centres[0] + centres[1]) / 2
    torch.testing.assert_close(medium(mid[None]).sigma_t[0],
                               (ours.sigma_t[0] + ours.sigma_t[1]) / 2, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("g_from_code", [False, True])
def test_a_latent_medium_gives_each_code_its_own_g_only_when_asked(g_from_code):
    """With ``g_from_code`` a code's g is ``G_MAX tanh(g_shared + w . z)``: every code starts
    at the plain medium's g (w = 0), the gradient reaches w at once and the code once w has
    moved, and then two codes differ in g; without it one g serves every code (the phase's single
    parameter)."""
    torch.manual_seed(3)
    medium = LatentVoxelMedium({"phase": "hg", "chromatic": True}, latent_dim=4,
                               resolutions=[4], density_resolution=8, g_from_code=g_from_code)
    density = torch.rand(8, 8, 8, 1) + 0.5
    a, b = torch.randn(4, requires_grad=True), torch.randn(4)
    assert float(medium.voxels_for(density, a).g_shared.detach()) == 0.0  # both start at g = 0
    medium.voxels_for(density, a).g_shared.backward()
    if not g_from_code:
        assert medium.g_weights is None and a.grad is None
        return
    assert medium.g_weights.grad.abs().sum() > 0  # d g / d w = G_MAX z at the start
    assert not a.grad.any()  # d g / d z = G_MAX w: zero while w is
    with torch.no_grad():
        medium.g_weights.copy_(torch.tensor([0.5, -0.3, 0.2, 0.1]))
    medium.voxels_for(density, a).g_shared.backward()
    assert a.grad.abs().sum() > 0  # once w moves, the code gets g's gradient too
    with torch.no_grad():
        ga, gb = (medium.voxels_for(density, z).g_shared for z in (a, b))
        expected = G_MAX * torch.tanh(medium.g_shared + medium.g_weights @ a)
    torch.testing.assert_close(ga, expected)
    assert abs(float(ga - gb)) > 1e-3 and abs(float(ga)) < G_MAX
