"""The voxel medium of split stage 2 composes the neural medium's heads on its cells and
interpolates between them."""

from __future__ import annotations

import pytest
import torch

from nrt.modules.fields.medium import NeuralMedium
from nrt.modules.fields.voxel_medium import VoxelMedium
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
