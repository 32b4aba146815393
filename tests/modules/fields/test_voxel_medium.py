"""The voxel medium of split stage 2 composes the neural medium's heads on its cells and
interpolates between them."""

from __future__ import annotations

import math

import pytest
import torch

from nrt.modules.fields.latent_grid import CHECK_DRAWS, fold_offsets
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


def test_member_offsets_shift_each_members_features_and_follow_the_schedule():
    """``member_offsets``: member k's outputs are the decoder's MLP on ``f(x) + offset_k(x)``
    (a new code reads ``f(x)`` alone); the gradient of member k's medium reaches its own
    offset only; the offsets' prior is the mean over members and cells of ``|offset_k|^2``;
    a doubling resamples the offsets with the features, and a state saved at the finer grid
    loads into a fresh medium."""
    torch.manual_seed(4)
    k_members, features = 3, 5
    medium = LatentVoxelMedium({"phase": "hg", "chromatic": True}, latent_dim=2,
                               features=features, resolutions=[4, 8], upsample_at=[0.5],
                               density_resolution=8, members=k_members, member_offsets=True)
    decoder = medium.modulation
    assert medium.member_offsets == k_members and not decoder.offsets.any()
    with torch.no_grad():
        decoder.net[-1].weight.normal_(0, 0.5)  # a trained output layer
        decoder.offsets.normal_(0, 0.2)
    code, density = torch.randn(2), torch.rand(8, 8, 8, 1) + 0.5
    torch.testing.assert_close(  # member 1's features are shifted by its own offset
        decoder.on_cells(4, code, 1),
        decoder._decode(decoder.values + decoder.offsets[..., features:2 * features], code))
    assert not torch.allclose(decoder.on_cells(4, code, 1), decoder.on_cells(4, code))
    medium.voxels_for(density, code, 1).stacked.sum().backward()
    grad = decoder.offsets.grad.reshape(4, 4, 4, k_members, features).abs().sum((0, 1, 2, 4))
    assert grad[1] > 0 and grad[0] == 0 and grad[2] == 0
    per_member = decoder.offsets.detach().reshape(64, k_members, features).square().sum(-1)
    torch.testing.assert_close(medium.offset_square(), per_member.mean())
    torch.testing.assert_close(medium.offset_square(torch.tensor([0, 2])),
                               per_member[:, [0, 2]].mean())
    assert medium.follow_schedule(0.6, None) and medium.resolution == 8
    assert decoder.offsets.shape == (8, 8, 8, k_members * features)
    fresh = LatentVoxelMedium({"phase": "hg", "chromatic": True}, latent_dim=2,
                              features=features, resolutions=[4, 8], upsample_at=[0.5],
                              density_resolution=8, members=k_members, member_offsets=True)
    fresh.load_state_dict(medium.state_dict())
    assert torch.equal(fresh.modulation.offsets, decoder.offsets)
    plain = LatentVoxelMedium({"phase": "hg", "chromatic": True}, latent_dim=2,
                              resolutions=[4], density_resolution=8, members=k_members)
    assert plain.member_offsets == 0 and plain.modulation.offsets is None
    with pytest.raises(ValueError, match="no member offsets"):
        plain.voxels_for(density, code, 0)


def folding_medium(members: int) -> LatentVoxelMedium:
    """A latent medium with ``members`` offsets, a trained output layer and random offsets."""
    medium = LatentVoxelMedium({"phase": "hg", "chromatic": True}, latent_dim=2, features=4,
                               resolutions=[4], density_resolution=8, members=members,
                               member_offsets=True)
    with torch.no_grad():
        medium.modulation.net[-1].weight.normal_(0, 0.5)
        medium.modulation.offsets.normal_(0, 0.2)
    return medium


def test_folding_one_offset_shared_by_every_member_recovers_it_exactly():
    """When every member carries the same offset o, the shared features f + o decode every
    member exactly: the fold must find a decoder whose codes alone reproduce the members'
    media, then hold no offsets. Adam through the MLP approaches that exact fit slowly
    (measured, drawing 4096 cells a member a step: 4.3e-4 of the start after 1000 steps,
    3.5e-4 after 2000); the test asks 1000 steps for 2e-3, 4x what they reach. The
    members' cells are weighed by a density that is zero on half of them."""
    torch.manual_seed(6)
    medium = folding_medium(3)
    decoder = medium.modulation
    with torch.no_grad():
        decoder.offsets.copy_(decoder.member_offset(0).repeat(1, 1, 1, 3))
    codes = torch.randn(3, 2)
    densities = torch.rand(3, 8, 8, 8, 1) * (torch.arange(8) < 4).view(1, 8, 1, 1, 1)
    targets = [medium.voxels_for(densities[k], codes[k], k).stacked.detach() for k in range(3)]
    start, end = medium.fold_offsets(densities, codes, steps=1000, lr=1e-2)
    assert start > 1e-2 and end < 2e-3 * start, (start, end)
    assert medium.member_offsets == 3 and not decoder.offsets.any()
    for k in range(3):  # a member decodes from its code alone as before, where it has density
        error = (medium.voxels_for(densities[k], codes[k]).stacked - targets[k]).abs()
        relative = (densities[k] * error).sum() / (densities[k] * targets[k].abs()).sum()
        assert relative < 0.01, (k, float(relative))


def test_folding_distinct_offsets_brings_the_codes_closer_to_their_members():
    """Distinct offsets: the shared decoder can only approximate them; the fold lowers the
    density-weighted error of every code's medium against its member's; a fit that would end
    above its start is undone; a decoder without offsets is refused."""
    torch.manual_seed(7)
    medium = folding_medium(4)
    codes, densities = torch.randn(4, 2), torch.rand(4, 8, 8, 8, 1)
    start, end = medium.fold_offsets(densities, codes, steps=200, lr=1e-2)
    assert end < 0.99 * start, (start, end)
    small = folding_medium(4)  # offsets of 1e-4 and a rate of 1: the fit would overshoot
    with torch.no_grad():
        small.modulation.offsets.mul_(5e-4)
    shared = small.modulation.values.detach().clone()
    start, end = small.fold_offsets(densities, codes, steps=5, lr=1.0)
    assert end == start and torch.equal(small.modulation.values, shared)  # undone
    assert not small.modulation.offsets.any()
    plain = LatentVoxelMedium({"phase": "hg", "chromatic": True}, latent_dim=2,
                              resolutions=[4], density_resolution=8, members=4)
    with pytest.raises(ValueError, match="no member offsets"):
        plain.fold_offsets(densities, codes, steps=1, lr=1e-2)


def test_a_member_without_density_leaves_the_fold_and_the_others_still_fold():
    """A member whose density is zero on every cell has no output that matters: the fold
    leaves it out (no draw from an all-zero row), folds the others as far as without it, and
    refuses weights that are zero everywhere, negative or not finite."""
    torch.manual_seed(8)
    codes, densities = torch.randn(4, 2), torch.rand(4, 8, 8, 8, 1)
    densities[2] = 0.0
    with_empty = folding_medium(4)
    without = folding_medium(4)
    without.load_state_dict(with_empty.state_dict())
    start, end = with_empty.fold_offsets(densities, codes, steps=200, lr=1e-2)
    assert math.isfinite(end) and end < 0.5 * start, (start, end)
    keep = [0, 1, 3]  # the same fit without member 2: the same objective, start and end
    decoder = without.modulation
    with torch.no_grad():
        grid = decoder.offsets.shape[:3]
        offsets = decoder.offsets.reshape(*grid, 4, -1)[..., keep, :].reshape(*grid, -1)
    decoder.offsets = torch.nn.Parameter(offsets.clone())
    alone = fold_offsets(decoder, codes[keep], densities[keep], steps=200, lr=1e-2)
    assert alone == pytest.approx((start, end), rel=1e-5)
    for bad, match in ((torch.zeros_like(densities), "zero on every cell"),
                       (-densities, "finite and >= 0"),
                       (densities.masked_fill(densities > 0.5, math.nan), "finite and >= 0")):
        with pytest.raises(ValueError, match=match):
            folding_medium(4).fold_offsets(bad, codes, steps=1, lr=1e-2)


def test_a_fold_with_a_kernel_decodes_codes_near_a_member_near_its_medium():
    """With a kernel the fold also fits each member's output at codes drawn around its code:
    at fresh codes near each member (other draws of the same kernel) the folded decoder's
    density-weighted error against that member's medium is smaller than after the fold at
    the codes alone, while the fold's objective (at the codes and at fixed draws around
    them) still falls. Measured over torch seeds 9-16: the near error 0.37-0.74x the plain
    fold's (mean 0.52), the objective ending at 0.18-0.62x its start (the plain fold's ends
    below 0.5x: fitting around the codes costs exactness at them); the test asks 0.8x and
    0.75x, above the largest of either. The kernel is asked for the members that have
    density, by their index among all members: once for the objective's draws, then once a
    step."""
    torch.manual_seed(13)
    codes, densities = torch.randn(4, 2), torch.rand(4, 8, 8, 8, 1)
    densities[2] = 0.0
    asked = []

    def kernel(members: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        asked.append(members.tolist())
        return codes[members] + 0.3 * torch.randn(len(members), 2, generator=generator)

    plain, smooth = folding_medium(4), folding_medium(4)
    smooth.load_state_dict(plain.state_dict())
    targets = [plain.voxels_for(densities[k], codes[k], k).stacked.detach() for k in range(4)]
    plain.fold_offsets(densities, codes, steps=300, lr=1e-2)
    start, end = smooth.fold_offsets(densities, codes, steps=300, lr=1e-2, kernel=kernel)
    assert end < 0.75 * start, (start, end)
    assert asked[0] == [0] * CHECK_DRAWS + [1] * CHECK_DRAWS + [3] * CHECK_DRAWS  # the check
    assert len(asked) == 301 and all(m == [0, 1, 3] for m in asked[1:])  # a draw a step
    generator = torch.Generator().manual_seed(1)

    def near_error(medium: LatentVoxelMedium) -> float:
        """The mean over members with density and 16 near codes each of the relative
        density-weighted error against the member's medium."""
        errors = []
        for k in (0, 1, 3):
            for _ in range(16):
                code = codes[k] + 0.3 * torch.randn(2, generator=generator)
                error = (medium.voxels_for(densities[k], code).stacked - targets[k]).abs()
                errors.append(float((densities[k] * error).sum()
                                    / (densities[k] * targets[k].abs()).sum()))
        return sum(errors) / len(errors)

    with torch.no_grad():
        plain_error = near_error(plain)
        generator.manual_seed(1)
        smooth_error = near_error(smooth)
    assert smooth_error < 0.8 * plain_error, (smooth_error, plain_error)
