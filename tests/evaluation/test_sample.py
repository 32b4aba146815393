"""nrt-sample: the Gaussian over latent codes, sampled media that Mitsuba renders and loads,
FID with the real weights, the interpolation strip, the reconstruction score and the
command's errors.

Media are decoded by :class:`TruthPCA`, an exact linear decoder of the test family's own
ground truths (codes = the members' principal-component coordinates): it satisfies the
generative stage-2 contract (``codes``, ``member_names``, ``property_grids_for``), so the
whole sampling path runs on known media, independent of training. Because it is exact,
each member's reconstruction MSE is 0 up to float rounding, which pins the pairing of
codes, members and ground truths.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from nrt.data.exr import read_exr
from nrt.data.family import load_family
from nrt.data.grids import PROPERTY_KEYS, load_property_grids
from nrt.data.media import medium_grids
from nrt.errors import ConfigError, NrtError
from nrt.evaluation.latent_gaussian import (
    auto_shrinkage,
    fit_latent_gaussian,
    scott_bandwidth,
)
from nrt.evaluation.sample import (
    AUTO_FOLD_STEPS,
    FamilyData,
    SampleSettings,
    check_medium,
    check_unseen,
    load_family_data,
    make_fid,
    sample_media,
    unseen_media,
    white_of,
)
from nrt.weights import FID_FILE, weights_dir
from tests.conftest import GENERATIVE_FAMILY, SMALL_FAMILY, cli_in_process, compose_config

pytestmark = pytest.mark.integration

SCENE = ("preset=tiny", "scene=family", *SMALL_FAMILY)
"""The session's test family (conftest ``family_dir``): the tiny preset's K = 4 members."""
HAVE_FID = (weights_dir() / FID_FILE).is_file()
NEEDS_FID = pytest.mark.skipif(
    not HAVE_FID, reason=f"the FID InceptionV3 weights are absent from {weights_dir()}: run "
    "nrt-weights once to fetch them (FID then runs with the real weights)")


class TruthPCA:
    """Decodes a code z (d_z,) to ``mean + z @ basis`` over the members' flattened true
    grids (basis: their top d_z principal directions), clamped to a valid medium
    (sigma >= 0, |g| <= 0.95). The members' codes are their own coordinates, so each
    decodes to its ground truth."""

    def __init__(self, data: FamilyData, dim: int = 4):
        flat = torch.stack([self.flatten(t) for t in data.truths]).double()
        self.shapes = {k: tuple(data.truths[0][k].shape) for k in PROPERTY_KEYS}
        self.mean = flat.mean(0)
        self.basis = torch.linalg.svd(flat - self.mean, full_matrices=False)[2][:dim]
        self.codes = ((flat - self.mean) @ self.basis.T).float()
        self.names = [m.name for m in data.family.members]

    @staticmethod
    def flatten(grids: dict) -> torch.Tensor:
        return torch.cat([torch.as_tensor(grids[k]).flatten() for k in PROPERTY_KEYS])

    def member_names(self) -> list[str]:
        return list(self.names)

    def medium_bbox(self) -> None:
        return None

    def member_property_grids(self, member: int, resolution: int) -> dict:
        return self.property_grids_for(self.codes[member], resolution)

    def property_grids_for(self, code: torch.Tensor, resolution: int) -> dict:
        flat, out, start = self.mean + code.double() @ self.basis, {}, 0
        for key, shape in self.shapes.items():
            size = int(np.prod(shape))
            out[key] = flat[start:start + size].reshape(shape).float()
            start += size
        out["sigma_a"], out["sigma_s"] = out["sigma_a"].clamp_min(0), out["sigma_s"].clamp_min(0)
        out["g"] = out["g"].clamp(-0.95, 0.95)
        return out


class ExactMembers(TruthPCA):
    """TruthPCA whose members' own media are their ground truths bit for bit (new codes
    still decode through the PCA)."""

    def __init__(self, data: FamilyData):
        super().__init__(data)
        self.truths = data.truths

    def member_property_grids(self, member: int, resolution: int) -> dict:
        return {k: torch.as_tensor(v).clone() for k, v in self.truths[member].items()
                if k in PROPERTY_KEYS}


# ------------------------------------------------------------------ the Gaussian fit
def test_gaussian_fit_reproduces_a_known_mean_and_covariance():
    """K = 20000 codes of a known N(mu, Sigma), d_z = 4: the fit's mean and covariance
    agree with mu and Sigma within 4 standard errors (se of a mean: sqrt(Sigma_ii / K);
    of a covariance entry: sqrt((Sigma_ii Sigma_jj + Sigma_ij^2) / K)), and the fit's own
    samples reproduce its moments the same way. No shrinkage: K > d_z."""
    k, gen = 20_000, torch.Generator().manual_seed(3)
    mu = torch.tensor([0.5, -1.0, 0.2, 2.0], dtype=torch.float64)
    a = torch.tensor([[1.0, 0, 0, 0], [0.6, 0.5, 0, 0], [-0.3, 0.2, 0.3, 0],
                      [0.1, -0.4, 0.2, 0.8]], dtype=torch.float64)
    sigma = a @ a.T
    codes = mu + torch.randn(k, 4, generator=gen, dtype=torch.float64) @ a.T
    fit = fit_latent_gaussian(codes)
    assert fit.shrinkage == 0.0 and fit.count == k

    def close(mean: torch.Tensor, cov: torch.Tensor, n: int) -> None:
        var = torch.diagonal(sigma)
        assert ((mean - mu).abs() <= 4 * (var / n).sqrt()).all(), (mean, mu)
        se = ((var[:, None] * var[None, :] + sigma**2) / n).sqrt()
        assert ((cov - sigma).abs() <= 4 * se).all(), (cov, sigma)

    close(fit.mean, fit.cov, k)
    drawn = fit.sample(k, seed=5).double()
    close(drawn.mean(0), torch.cov(drawn.T), k)
    assert torch.equal(fit.sample(3, seed=5), fit.sample(3, seed=5))  # seeded


def test_few_codes_shrink_toward_the_diagonal_and_leave_the_codes_span():
    """K = 3 codes in d_z = 4 span a plane: the sample covariance S has rank 2. The fit
    mixes in diag(S) with lam = (d_z - K + 1) / d_z = 1/2, which is positive definite, and
    its samples leave the plane (a Gaussian with S alone never would)."""
    codes = torch.tensor([[0.0, 0.1, -0.2, 0.3], [0.4, -0.1, 0.0, 0.1], [-0.2, 0.3, 0.5, 0.0]])
    fit = fit_latent_gaussian(codes)
    s = torch.cov(codes.double().T)
    assert fit.shrinkage == auto_shrinkage(3, 4) == 0.5
    torch.testing.assert_close(fit.cov, 0.5 * s + 0.5 * torch.diag(torch.diagonal(s)))
    assert torch.linalg.matrix_rank(s) == 2
    assert torch.linalg.eigvalsh(fit.cov).min() > 1e-4
    drawn = fit.sample(200, seed=0).double()
    assert torch.isfinite(drawn).all()
    basis = torch.linalg.svd(codes.double() - codes.double().mean(0))[2][:2]  # the plane
    off = drawn - fit.mean
    off_plane = off - off @ basis.T @ basis
    assert off_plane.norm(dim=1).mean() > 0.1 * off.norm(dim=1).mean()
    assert auto_shrinkage(5, 4) == 0.0 and auto_shrinkage(4, 4) == 0.25
    assert fit_latent_gaussian(codes, shrinkage=0.0).shrinkage == 0.0


def test_temperature_scales_the_spread_and_one_is_the_fit_itself():
    """Temperature t draws N(mu, t^2 Sigma): at t = 0.5, 20000 draws' covariance agrees with
    Sigma / 4 within 4 standard errors of a covariance entry; t = 1 draws exactly what the
    plain call draws (the same seed, the same codes)."""
    gen = torch.Generator().manual_seed(1)
    codes = torch.randn(40, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 0.5, 2.0])
    fit = fit_latent_gaussian(codes)
    k, t = 20_000, 0.5
    drawn = fit.sample(k, seed=2, temperature=t).double()
    sigma = t * t * fit.cov
    var = torch.diagonal(sigma)
    se = ((var[:, None] * var[None, :] + sigma**2) / k).sqrt()
    assert ((torch.cov(drawn.T) - sigma).abs() <= 4 * se).all()
    assert ((drawn.mean(0) - fit.mean).abs() <= 4 * (var / k).sqrt()).all()
    assert torch.equal(fit.sample(5, seed=3, temperature=1.0), fit.sample(5, seed=3))


def test_smoothed_bootstrap_runs_from_the_codes_to_the_gaussian():
    """Bandwidth h = 0 draws only the learned codes themselves, each once in every K draws;
    any h keeps the codes' mean and, up to the divisor, their covariance:
    (S_K + h^2 Sigma) / (1 + h^2), S_K the codes' covariance with divisor K, checked on
    20000 draws at h = 0.5 and h = 3 within 4 standard errors of a covariance entry (the
    draws' own: the sd of the products of centred entries over sqrt(20000))."""
    gen = torch.Generator().manual_seed(4)
    codes = torch.randn(8, 3, generator=gen, dtype=torch.float64)
    fit = fit_latent_gaussian(codes)
    same = fit.sample(200, seed=0, bandwidth=0.0).double()
    dist = torch.cdist(same, codes)
    assert (dist.min(dim=1).values < 1e-6).all()
    for start in range(0, 200 - 8, 8):  # rounds of K = 8 draws: every code once
        assert sorted(dist[start:start + 8].argmin(dim=1).tolist()) == list(range(8))
    centred = codes - codes.mean(0)
    s_k = centred.T @ centred / len(codes)
    k = 20_000
    for h in (0.5, 3.0):
        drawn = fit.sample(k, seed=1, bandwidth=h).double()
        sigma = (s_k + h * h * fit.cov) / (1 + h * h)
        var = torch.diagonal(sigma)
        off = drawn - drawn.mean(0)
        se = (off[:, :, None] * off[:, None, :]).std(dim=0) / k**0.5
        assert ((torch.cov(drawn.T) - sigma).abs() <= 4 * se).all(), h
        assert ((drawn.mean(0) - fit.mean).abs() <= 4 * (var / k).sqrt()).all(), h
    assert scott_bandwidth(16, 16) == pytest.approx(16 ** -0.05)
    assert 0.86 < scott_bandwidth(16, 16) < 0.88


def test_draws_around_a_code_are_the_bootstrap_kernel_at_that_code():
    """``around`` draws the smoothed bootstrap's kernel at each given code: for code k,
    mean ``mu + (z_k - mu) / sqrt(1 + h^2)`` and covariance ``h^2 Sigma / (1 + h^2)``,
    checked on 20000 draws at h = 0.5 within 4 standard errors (as above); h = 0 gives the
    code itself. ``sample`` with a bandwidth reads the same kernel: the same generator
    state gives the same draws."""
    gen = torch.Generator().manual_seed(5)
    codes = torch.randn(6, 3, generator=gen, dtype=torch.float64)
    fit = fit_latent_gaussian(codes)
    members = torch.tensor([1, 4, 4])
    same = fit.around(members, 0.0, torch.Generator().manual_seed(0)).double()
    torch.testing.assert_close(same, codes[members], rtol=0, atol=1e-6)
    k, h = 20_000, 0.5
    drawn = fit.around(torch.full((k,), 4), h, torch.Generator().manual_seed(1)).double()
    mean = fit.mean + (codes[4] - fit.mean) / (1 + h * h) ** 0.5
    sigma = h * h * fit.cov / (1 + h * h)
    off = drawn - drawn.mean(0)
    se = (off[:, :, None] * off[:, None, :]).std(dim=0) / k**0.5
    assert ((torch.cov(drawn.T) - sigma).abs() <= 4 * se).all()
    assert ((drawn.mean(0) - mean).abs() <= 4 * (torch.diagonal(sigma) / k).sqrt()).all()
    gen = torch.Generator().manual_seed(2)
    pick = torch.randperm(6, generator=gen)
    assert torch.equal(fit.sample(6, seed=2, bandwidth=h), fit.around(pick, h, gen))


@pytest.mark.parametrize("bad", ["half", -0.1, 1.5, True])
def test_bad_shrinkage_and_too_few_codes_are_refused(bad):
    with pytest.raises(ConfigError, match="shrinkage"):
        fit_latent_gaussian(torch.zeros(3, 4), shrinkage=bad)
    with pytest.raises(ConfigError, match="at least 2 codes"):
        fit_latent_gaussian(torch.zeros(1, 4))


@pytest.mark.parametrize("settings, key", [
    (SampleSettings(fold_steps=-1), "fold.steps=-1"),
    (SampleSettings(fold_steps=None), "fold.steps=None"),
    (SampleSettings(fold_lr=0.0), "fold.lr=0.0"),
    (SampleSettings(fold_lr="fast"), "fold.lr='fast'"),
    (SampleSettings(fold_bandwidth=-0.5), "fold.bandwidth=-0.5"),
    (SampleSettings(fold_bandwidth="wide"), "fold.bandwidth='wide'")])
def test_bad_fold_settings_name_their_key(settings, key):
    with pytest.raises(NrtError, match=re.escape(key)):
        settings.check()


def test_settings_defaults_are_the_config_defaults():
    """``SampleSettings()`` is ``conf/sample.yaml`` as composed: code that builds settings
    without the CLI (the benchmarks) scores at the counts ``nrt-sample`` uses."""
    from dataclasses import asdict

    from nrt.cli.sample import settings_of

    assert asdict(settings_of(compose_config("sample"))) == asdict(SampleSettings())


def test_auto_folds_a_run_with_offsets_and_leaves_one_without():
    """``fold.steps=auto`` (the default) folds exactly where there are offsets to fold; a
    number is taken as given, whatever the run holds (0 samples the unfolded decoder)."""
    auto = SampleSettings()
    auto.check()
    assert auto.fold_steps == "auto"
    assert auto.fold_steps_for(member_offsets=True) == AUTO_FOLD_STEPS > 0
    assert auto.fold_steps_for(member_offsets=False) == 0
    for steps in (0, 5):
        given = SampleSettings(fold_steps=steps)
        given.check()
        assert given.fold_steps_for(True) == given.fold_steps_for(False) == steps
    with pytest.raises(NrtError, match=re.escape("fold.steps='always'")):
        SampleSettings(fold_steps="always").check()


def test_invalid_media_are_refused():
    good = {"sigma_a": torch.ones(2, 2, 2, 3), "sigma_s": torch.ones(2, 2, 2, 3),
            "g": torch.zeros(2, 2, 2)}
    check_medium(good, "a test")
    for key, value in (("sigma_a", -1.0), ("sigma_s", float("nan")), ("g", 1.0)):
        bad = {k: v.clone() for k, v in good.items()}
        bad[key].view(-1)[0] = value
        with pytest.raises(NrtError, match="not a valid medium"):
            check_medium(bad, "a test")


def test_white_ignores_the_few_views_with_the_sun():
    """White is the median of the images' maxima: one sun-lit view of five, 100x brighter,
    does not move it (the maximum would darken the other four to a fifth of the range)."""
    images = torch.full((5, 8, 8, 3), 0.5)
    images[:, 0, 0] = torch.tensor([0.8, 0.9, 1.0, 1.1, 1.2])[:, None]
    images[4, 1, 1] = 120.0
    assert white_of(images) == pytest.approx(1.0)


# ------------------------------------------------------------------ sampling a family
@pytest.fixture(scope="module")
def family_data(family_dir) -> FamilyData:
    cfg = compose_config("dataset", list(SCENE))
    return load_family_data(load_family(family_dir),
                            OmegaConf.to_container(cfg.scene.effects, resolve=True),
                            OmegaConf.to_container(cfg.scene, resolve=True))


@pytest.fixture(scope="module")
def sampled(family_data, tmp_path_factory) -> tuple:
    """sample_media on the exact decoder: 3 media, 1 view per sky, no FID (~5 s)."""
    out = tmp_path_factory.mktemp("sampled")
    settings = SampleSettings(n=3, views=1, interpolate_steps=5, interpolate_members=[0, 2])
    model = TruthPCA(family_data)
    return model, sample_media(model, family_data, settings, out, fid=None), out


def test_sampled_media_are_finite_valid_and_load_in_mitsuba(sampled, family_data):
    from nrt.mitsuba.variant import select_variant

    model, result, out = sampled
    mi = select_variant("auto")
    folders = sorted((out / "samples").iterdir())
    assert [f.name for f in folders] == ["sample000", "sample001", "sample002"]
    for i, folder in enumerate(folders):
        grids = load_property_grids(folder / "medium_grids.npz")  # validates the layout
        expected = check_medium(model.property_grids_for(result.samples[i], 24), "expected")
        for key in PROPERTY_KEYS:
            assert torch.isfinite(grids[key]).all()
            torch.testing.assert_close(grids[key], expected[key])
        assert (grids["sigma_a"] >= 0).all() and (grids["g"].abs() < 1).all()
        scene = mi.load_file(str(folder / "volumes" / "medium.xml"))  # loads as a volume
        assert scene.shapes()[0].interior_medium() is not None
        sigma_t = np.array(mi.VolumeGrid(str(folder / "volumes" / "sigma_t.vol")))
        truth_t = (grids["sigma_a"] + grids["sigma_s"]).numpy()
        np.testing.assert_allclose(sigma_t.reshape(truth_t.shape), truth_t, rtol=1e-6)
        renders = sorted(folder.glob("*.exr"))
        assert [r.name.split("_")[0] for r in renders] == ["sky0", "sky1"]
        for path in renders:
            img = read_exr(path)
            assert img.shape == (24, 24, 3) and np.isfinite(img).all() and img.min() >= 0


def test_samples_follow_the_fitted_gaussian(sampled):
    model, result, out = sampled
    saved = np.load(out / "latent_gaussian.npz")
    np.testing.assert_allclose(saved["codes"], model.codes.numpy())
    np.testing.assert_allclose(saved["samples"], result.samples.numpy())
    torch.testing.assert_close(result.samples, result.gaussian.sample(3, seed=0))
    assert result.metrics["gaussian_shrinkage"] == auto_shrinkage(4, 4)


def test_each_member_reconstructs_from_its_own_code(sampled):
    """The exact decoder gives MSE 0 (float rounding: < 1e-8 x100) for every member
    paired with its own ground truth; a mispairing would give the members' distance."""
    _, result, _ = sampled
    assert [r["name"] for r in result.members] == [f"family_seed{k}" for k in range(4)]
    for row in result.members:
        assert row["mse_sigma_t_x100"] < 1e-8, row
    assert result.metrics["recon_mse_sigma_t_x100"] < 1e-8


def test_interpolation_lies_between_its_endpoints(sampled):
    """Along z(t) the decoder is linear up to clamping, so MSE to A grows like t^2 and to
    B like (1 - t)^2 times the endpoints' MSE D; clamping a value toward the valid range
    only shortens distances. Asserted: the strip runs from A (MSE 0) to B (MSE 0), MSE to
    A rises and to B falls at every step, and MSE_A + MSE_B <= D (equality at the ends,
    (t^2 + (1 - t)^2) D for a linear blend): no step leaves the segment between them."""
    _, result, out = sampled
    rows = result.interpolation
    assert [r["t"] for r in rows] == pytest.approx([0, 0.25, 0.5, 0.75, 1])
    to_a = np.array([r["mse_sigma_t_to_a_x100"] for r in rows])
    to_b = np.array([r["mse_sigma_t_to_b_x100"] for r in rows])
    distance = to_a[-1]
    assert to_a[0] == 0 and to_b[-1] == 0 and distance > 1.0
    assert (np.diff(to_a) > 0).all() and (np.diff(to_b) < 0).all()
    assert (to_a + to_b <= distance * (1 + 1e-4)).all()
    assert result.metrics["interpolation_member_a"] == 0
    assert (out / "interpolation.png").is_file()


def test_pictures_show_every_sample_under_both_skies(sampled):
    from PIL import Image

    _, result, out = sampled
    for sky in ("sky0", "sky1"):
        pic = np.asarray(Image.open(out / f"samples_{sky}.png"))
        assert pic.shape == (2 * 24 + 2, 2 * 24 + 2, 3)  # 3 samples on a 2 x 2 grid
    strip = np.asarray(Image.open(out / "interpolation.png"))
    assert strip.shape == (2 * 24 + 2, 5 * 24 + 4 * 2, 3)  # 5 steps, a row per sky


def test_unseen_media_are_new_members_of_the_family(family_data, monkeypatch):
    """The unseen reference's media: drawn by the family's config from the seeds after its
    members' (the config draws the first member's ground truth again), valid, and each
    unlike every member (its sigma_t MSE to the nearest member's truth is of the order of
    the members' own spacing, not a rounding). The check that the config draws the family
    runs once: drawing after it resolves only the new media."""
    import nrt.evaluation.sample as sample
    from nrt.evaluation.evaluate import property_metrics

    data = FamilyData(family_data.family, family_data.cameras, family_data.truths,
                      family_data.effects, family_data.scene)
    resolved = []
    monkeypatch.setattr(sample, "medium_grids",
                        lambda spec: resolved.append(spec) or medium_grids(spec))
    check_unseen(data)
    assert len(resolved) == 1 and data.unseen_checked  # the first member, drawn again
    media = unseen_media(data, 2)
    assert len(media) == 2 and len(resolved) == 3  # the two new media only
    effects, truths = family_data.effects, family_data.truths
    for m in media:
        check_medium(m, "unseen medium")
        assert m["g"].shape == truths[0]["g"].shape

    def nearest(medium, skip=None):
        return min(property_metrics(medium, t, effects)["mse_sigma_t_x100"]
                   for j, t in enumerate(truths) if j != skip)
    apart = [nearest(t, skip=j) for j, t in enumerate(truths)]
    for m in media:
        assert nearest(m) > 0.05 * min(apart), (nearest(m), apart)
    assert not torch.equal(media[0]["sigma_s"], media[1]["sigma_s"])


@pytest.mark.parametrize("key, value, match", [
    ("family", None, "holds no scene.family"),
    ("seed", 7, "does not draw the first member"),
])
def test_unseen_media_need_the_familys_own_config(family_data, key, value, match):
    """A config without a family, or one whose first member is another medium (another
    seed), is refused."""
    scene = {k: v for k, v in family_data.scene.items() if k != key}
    if value is not None:
        scene[key] = value
    data = FamilyData(family_data.family, family_data.cameras, family_data.truths,
                      family_data.effects, scene)
    with pytest.raises(NrtError, match=match):
        unseen_media(data, 1)


@NEEDS_FID
@pytest.mark.slow
def test_fid_columns_with_the_real_weights(family_data, tmp_path):
    """Both FID columns and the true media's and the reconstructions' references run with
    the real InceptionV3: finite, positive, on the stated crop counts (~50 s: ~70
    InceptionV3 passes). ExactMembers' members are their ground truths bit for bit, and the
    two references share render seeds and crop positions, so they score alike: what
    ``*_recon`` adds to ``*_truth`` is the reconstruction's. (Grids equal only to float
    rounding would not do: a density a rounding apart turns some of Mitsuba's tracking
    decisions, and FID on 2 crops moved 0.7 % with it.)"""
    settings = SampleSettings(n=2, views=1, fid_n_crops=1, fid_real_views=2,
                              interpolate_steps=2, fid_recon_reference=True,
                              fid_unseen_reference=True)
    fid = make_fid(settings, family_data.cameras)
    result = sample_media(ExactMembers(family_data), family_data, settings, tmp_path, fid)
    m = result.metrics
    for col in ("train", "novel"):
        for key in (f"fid_{col}_illumination", f"fid_{col}_illumination_truth",
                    f"fid_{col}_illumination_recon"):
            assert np.isfinite(m[key]) and m[key] > 0, (key, m[key])
        assert m[f"fid_{col}_illumination_recon"] == pytest.approx(
            m[f"fid_{col}_illumination_truth"], rel=1e-6)
        # other media on the same render seeds and crops: another score
        unseen = m[f"fid_{col}_illumination_unseen"]
        assert np.isfinite(unseen) and unseen > 0
        assert unseen != pytest.approx(m[f"fid_{col}_illumination_truth"], rel=1e-6)
        assert m[f"fid_{col}_real_crops"] == 4 * 2  # K members x 2 views x 1 crop
        assert m[f"fid_{col}_sample_crops"] == 2
    assert m["fid_crop"] == 16


# ------------------------------------------------------------------ the command's errors
def run_sample(tmp: Path, *overrides: str, env: dict | None = None) -> tuple[int, str]:
    """``nrt-sample`` in this process (:func:`~tests.conftest.cli_in_process`: its CLI entry
    point, Hydra and all; a subprocess would spend most of its time importing): exit status
    and stderr."""
    proc = cli_in_process("sample", *overrides,
                          env={"NRT_OUTPUT_DIR": str(tmp / "outputs"), **(env or {})})
    return proc.returncode, proc.stderr


def fake_run(folder: Path, info: dict, overrides: tuple[str, ...] = ()) -> Path:
    """A run folder as nrt-train leaves it (run.json, .hydra/config.yaml), without training."""
    (folder / ".hydra").mkdir(parents=True)
    cfg = compose_config("train", ["preset=tiny", *overrides])
    (folder / ".hydra" / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=False))
    (folder / "run.json").write_text(json.dumps(info))
    return folder


@pytest.mark.parametrize("case", ["missing", "not_a_run", "single", "generative_ea", "n0",
                                  "cold", "wide"])
def test_errors_exit_2_with_one_paragraph(tmp_path, case):
    family = {"mode": "generative", "family_dir": str(tmp_path / "family"), "scene": "family",
              "environments": ["sky0"], "members": []}
    runs = {
        "missing": (tmp_path / "nowhere", "does not exist"),
        "not_a_run": (tmp_path, "is not a run folder of nrt-train"),
        "single": (fake_run(tmp_path / "single", {"stage": "rte", "scene": "default",
                                                  "mode": "single"}),
                   "nrt-sample needs a generative stage-2 run"),
        "generative_ea": (fake_run(tmp_path / "gen_ea", {"stage": "ea", **family},
                                   ("scene=family", "mode=generative")),
                          "stage=rte mode=generative scene=family init.ea_ckpt="),
    }
    bad = {"n0": ("n=0", "n=0"), "cold": ("gaussian.temperature=0", "gaussian.temperature=0"),
           "wide": ("gaussian.bandwidth=-1", "gaussian.bandwidth=-1")}
    override, needle = bad.get(case, (None, None))
    run, needle = runs.get(case, (tmp_path, needle))
    code, err = run_sample(tmp_path, f"run={run}", *([override] if override else []))
    assert code == 2 and "nrt: error:" in err and needle in err, err[-2000:]
    assert "Traceback" not in err
    assert not list(tmp_path.glob("**/sample/*")), "a failed start left a folder behind"


def test_missing_fid_weights_name_the_file_and_nrt_weights(family_data, tmp_path):
    """A generative stage-2 run folder over the test family, with the weights folder
    pointed at an empty one: refused before any model is loaded or medium rendered."""
    family = {"stage": "rte", "mode": "generative", "scene": "family",
              "family_dir": str(family_data.family.root), "environments": ["sky0"]}
    run = fake_run(tmp_path / "gen_rte", family, ("scene=family", "mode=generative"))
    empty = tmp_path / "no_weights"
    code, err = run_sample(tmp_path, f"run={run}",
                           env={"NRT_WEIGHTS_DIR": str(empty)})
    assert code == 2 and "nrt: error:" in err and "nrt-weights" in err, err[-2000:]
    assert str(empty / FID_FILE) in err and "fid.enabled=false" in err


# ---------------------------------------------- the real path: a generative stage-2 run
TRAIN_SHORT = ("budget.val_every=100", "budget.val_views=2", "budget.checkpoint_every=100",
               "render.progress=false", "trainer.enable_progress_bar=false",
               "logger=[tensorboard]")


@pytest.fixture(scope="module")
def generative_run(family_data, tmp_path_factory) -> tuple[Path, dict]:
    """``nrt-train stage=ea mode=generative`` (100 steps), then ``stage=rte`` from it (100
    steps), then ``nrt-sample`` on the stage-2 run, all through the real commands on the
    test family (~1.5-2 min on 2 shared cores): the sample folder and run.json."""
    out = tmp_path_factory.mktemp("generative_runs")
    env = {**os.environ, "NRT_OUTPUT_DIR": str(out)}
    data_dir = f"paths.data_dir={family_data.family.root.parent}"
    train = [sys.executable, "-m", "nrt.cli.train", *GENERATIVE_FAMILY, *SMALL_FAMILY, data_dir,
             *TRAIN_SHORT]
    ea = subprocess.run([*train, "stage=ea", "stage.steps=100"], env=env,
                        capture_output=True, text=True, timeout=600)
    assert ea.returncode == 0, ea.stderr[-3000:]
    ea_ckpt = next((out / "family" / "ea").glob("*/checkpoints/last.ckpt"))
    rte = subprocess.run([*train, "stage=rte", "budget.rte.steps=100",
                          f"init.ea_ckpt={ea_ckpt}"], env=env, capture_output=True, text=True,
                         timeout=600)
    assert rte.returncode == 0, rte.stderr[-3000:]
    run = next((out / "family" / "rte").iterdir())
    fid = ["fid.n_crops=1", "fid.real_views=2"] if HAVE_FID else ["fid.enabled=false"]
    sample = subprocess.run([sys.executable, "-m", "nrt.cli.sample", f"run={run}", "n=3",
                             "render.views=1", "interpolate.steps=7", *fid], env=env,
                            capture_output=True, text=True, timeout=600)
    assert sample.returncode == 0, sample.stderr[-3000:]
    folders = list((run / "sample").iterdir())
    assert len(folders) == 1, folders
    return folders[0], json.loads((run / "run.json").read_text())


@pytest.mark.slow
def test_real_samples_render_and_load_in_mitsuba(generative_run):
    from nrt.mitsuba.variant import select_variant

    folder, _ = generative_run
    mi = select_variant("auto")
    for sample in sorted((folder / "samples").iterdir()):
        grids = load_property_grids(sample / "medium_grids.npz")
        check_medium(grids, sample.name)  # finite, sigma >= 0, |g| < 1
        assert float(grids["sigma_a"].sum() + grids["sigma_s"].sum()) > 0  # not empty
        mi.load_file(str(sample / "volumes" / "medium.xml"))
        for path in sample.glob("*.exr"):
            assert np.isfinite(read_exr(path)).all()
    metrics = json.loads((folder / "metrics.json").read_text())["metrics"]
    if HAVE_FID:
        assert all(np.isfinite(metrics[f"fid_{c}_illumination"]) for c in ("train", "novel"))


@pytest.mark.slow
def test_real_reconstruction_matches_the_runs_own_property_metrics(generative_run):
    """nrt-sample decodes each member from its code and scores it against its ground truth;
    stage 2's validation callback scored the same checkpoint's members by its own path
    (PropertyMetrics): the two agree (float32 grids, MSE in float64: 1e-4 relative)."""
    folder, info = generative_run
    report = json.loads((folder / "metrics.json").read_text())
    final = info["final_metrics"]
    for row in report["members"]:
        for key in ("sigma_a", "sigma_s", "sigma_t"):
            logged = final[f"val/mse_{key}_x100_member{row['member']}"]
            assert row[f"mse_{key}_x100"] == pytest.approx(logged, rel=1e-4, abs=1e-6)


@pytest.mark.slow
def test_real_interpolation_moves_from_one_endpoint_to_the_other(generative_run):
    """Media decoded along z(t) = (1 - t) z_a + t z_b (7 steps) between the two codes
    farthest apart. The property MSE (sigma_a, sigma_s, sigma_t) to A must rise and to B
    fall at every step, within a tolerance of 0.5 % of the endpoints' MSE D per step, and
    MSE_A + MSE_B must stay <= 1.05 D (a linear blend gives (t^2 + (1 - t)^2) D <= D).

    Why 0.5 %: the decoder is smooth but not linear in z (sigma = rho_EA(x; z) exp(m(x, z))),
    so MSE_A grows faster than t^2 near one end and flatter near the other. Measured on the
    tiny family after 300 + 300 steps, over all 6 member pairs, 7 steps and the three
    properties: every step moved the right way, the smallest by 0.73 % of D (0.25 % with
    a decoder that re-bakes the density without gradient; a linear blend's
    smallest is (1/6)^2 D = 2.8 %), and MSE_A + MSE_B never exceeded D. A reversal larger
    than 0.5 % of D, or a sum over 1.05 D, is a medium leaving the segment between the
    endpoints, not the decoder's curvature."""
    folder, _ = generative_run
    rows = json.loads((folder / "metrics.json").read_text())["interpolation"]
    assert len(rows) == 7 and rows[0]["t"] == 0 and rows[-1]["t"] == 1
    for key in ("sigma_a", "sigma_s", "sigma_t"):
        to_a = np.array([r[f"mse_{key}_to_a_x100"] for r in rows])
        to_b = np.array([r[f"mse_{key}_to_b_x100"] for r in rows])
        distance = to_a[-1]
        assert distance > 0 and to_a[0] == 0 and to_b[-1] == 0
        assert to_b[0] == pytest.approx(distance)
        assert (np.diff(to_a) >= -0.005 * distance).all(), (key, to_a)
        assert (np.diff(to_b) <= 0.005 * distance).all(), (key, to_b)
        assert (to_a + to_b <= 1.05 * distance).all(), (key, to_a + to_b)
