"""Image and medium metrics shared by training callbacks and evaluation.

Images are compared after the log tonemap ``y = log1p(x)`` (docs/conventions.md, "Image
comparison"): PSNR uses the tonemapped reference's range; SSIM and LPIPS take ``y`` divided by the
reference's maximum and clamped to [0, 1]. Images are (H, W, 3) linear radiance. FID
compares sets of images on random crops (:class:`FID`). The pretrained networks of LPIPS and
FID come from ``nrt-weights`` (:mod:`nrt.weights`).
"""

from __future__ import annotations

import math

import torch
from torchmetrics.functional.image import (
    peak_signal_noise_ratio,
    structural_similarity_index_measure,
)

from nrt.errors import NrtError
from nrt.physics.tonemap import log_tonemap


def psnr(pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """PSNR (dB) of log-tonemapped images, peak = the tonemapped reference's range."""
    y_pred, y_ref = log_tonemap(pred), log_tonemap(ref)
    data_range = (y_ref.max() - y_ref.min()).clamp_min(1e-8)
    return peak_signal_noise_ratio(y_pred, y_ref, data_range=float(data_range))


def unit_range(pred: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Log-tonemapped (H, W, 3) images as (1, 3, H, W) in [0, 1], scaled by the reference."""
    y_pred, y_ref = log_tonemap(pred.float()), log_tonemap(ref.float())
    scale = y_ref.max().clamp_min(1e-8)
    return tuple((y / scale).clamp(0, 1).permute(2, 0, 1).unsqueeze(0) for y in (y_pred, y_ref))


def ssim(pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """SSIM (Gaussian window 11, sigma 1.5) of (H, W, 3) images, log-tonemapped."""
    a, b = unit_range(pred, ref)
    return structural_similarity_index_measure(a, b, data_range=1.0)


class LPIPS:
    """LPIPS (v0.1, lower is better) of (H, W, 3) linear images, log-tonemapped.

    The network is the ``lpips`` package's with its linear layers and the ImageNet backbone
    (``alex`` or ``vgg``) that ``nrt-weights`` converted (:mod:`nrt.weights`); no model hub
    is contacted. When the weights are missing, the error names ``nrt-weights``.
    """

    def __init__(self, net: str = "alex", device: torch.device | str = "cpu"):
        from nrt.weights import load_lpips

        self.net = load_lpips(net).to(device)

    @torch.no_grad()
    def unit(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """LPIPS of (N, 3, H, W) images in [0, 1], one value per pair (N,)."""
        dev = next(self.net.parameters()).device
        return self.net(a.to(dev), b.to(dev), normalize=True).flatten()

    def __call__(self, pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        return self.unit(*unit_range(pred, ref))[0]


def frechet_distance(real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
    """Frechet distance of the Gaussians fitted to two feature sets (n1, d) and (n2, d):
    ``|mu1 - mu2|^2 + tr(S1) + tr(S2) - 2 tr((S1 S2)^(1/2))`` (unbiased covariances), in
    float64, the formula of torchmetrics' FID (a test pins the two together).

    ``tr((S1 S2)^(1/2))`` is the nuclear norm of ``A B^T`` for ``S1 = A^T A``,
    ``S2 = B^T B`` (centred, scaled features): an n1 x n2 SVD instead of a d x d
    eigendecomposition when there are fewer samples than dimensions (minutes on 2 CPU
    cores for d = 2048); with more samples, a symmetric d x d eigendecomposition.
    """
    real, fake = real.double(), fake.double()
    (n1, d), n2 = real.shape, fake.shape[0]
    if n1 < 2 or n2 < 2:
        raise NrtError(f"A Frechet distance needs at least 2 samples per set, got {n1} and {n2}.")
    mu1, mu2 = real.mean(0), fake.mean(0)
    a, b = (real - mu1) / math.sqrt(n1 - 1), (fake - mu2) / math.sqrt(n2 - 1)
    if n1 * n2 <= d * d:
        cross = torch.linalg.svdvals(a @ b.T).sum()
    else:
        evals, evecs = torch.linalg.eigh(a.T @ a)
        root = (evecs * evals.clamp_min(0).sqrt()) @ evecs.T
        cross = torch.linalg.eigvalsh(root @ (b.T @ b) @ root).clamp_min(0).sqrt().sum()
    return (mu1 - mu2).square().sum() + a.square().sum() + b.square().sum() - 2 * cross


class FID:
    """Frechet Inception distance (FID) between a set of real and a set of generated images,
    measured on random square crops: the InceptionV3 pool3 features (2048-d, the 2015-12-05
    TensorFlow graph FID is defined on) of torchmetrics' ``FrechetInceptionDistance``, with
    the weights that ``nrt-weights`` converted, and its formula (:func:`frechet_distance`).

    ``update(images, real=...)`` takes (H, W, 3) or (N, H, W, 3) images. With ``white=None``
    they are display-referred values in [0, 1]; with ``white=w`` they are linear radiance,
    mapped like every nrt image metric through the log tonemap, ``log1p(x) / log1p(w)``
    clamped to [0, 1], the same ``w`` for both sets (per-image scaling would hide brightness
    errors). From each image ``n_crops`` crops of ``crop`` x ``crop`` pixels are cut at
    random positions (seeded by ``seed``, one generator per set, so equal sets give equal
    crops), quantised to 8 bits as torchmetrics does and resized to 299x299 by
    torch-fidelity's TF1-compatible bilinear resize.

    ``compute()`` is FID in its usual unit (squared distance of pool3 features; lower is
    better, 0 for equal statistics); it needs at least 2 crops per set. FID is biased upward
    for few crops (the covariances are estimated from them): compare values only at equal
    crop counts, crop size and ``white``. ``reset(real=False)`` keeps the real set, to
    compare several generated sets with one real set. Cost: one InceptionV3 pass per crop
    (about 0.1-0.6 s on 2 CPU cores).
    """

    def __init__(self, crop: int = 64, n_crops: int = 8, white: float | None = None,
                 seed: int = 0, device: torch.device | str = "cpu", batch: int = 16):
        from torchmetrics.image.fid import NoTrainInceptionV3

        from nrt.weights import FIDELITY_NAME, fid_inception_path

        if crop < 16 or n_crops < 1:
            raise NrtError(f"FID needs crop >= 16 pixels and n_crops >= 1, got crop={crop}, "
                           f"n_crops={n_crops}.")
        if white is not None and not white > 0:
            raise NrtError(f"FID white must be a positive radiance (or None), got {white}.")
        self.crop, self.n_crops, self.white, self.seed, self.batch = (
            int(crop), int(n_crops), white, int(seed), int(batch))
        self.inception = NoTrainInceptionV3(
            FIDELITY_NAME, ["2048"], feature_extractor_weights_path=str(fid_inception_path()),
            antialias=False).to(device)
        self._features: dict[bool, list[torch.Tensor]] = {True: [], False: []}
        self._gen: dict[bool, torch.Generator] = {}
        self.reset()

    def reset(self, real: bool = True) -> None:
        """Forget the generated set, and the real one unless ``real=False``."""
        for side in (True, False) if real else (False,):
            self._features[side] = []
            self._gen[side] = torch.Generator().manual_seed(self.seed)

    def count(self, real: bool) -> int:
        return sum(len(f) for f in self._features[real])

    def crops(self, images: torch.Tensor, real: bool) -> torch.Tensor:
        """The (N * n_crops, 3, crop, crop) crops in [0, 1] that ``update`` measures."""
        x = images.detach().float().cpu()
        x = x.unsqueeze(0) if x.ndim == 3 else x
        if x.ndim != 4 or x.shape[-1] != 3:
            raise NrtError(f"FID takes (H, W, 3) or (N, H, W, 3) images, got {tuple(x.shape)}.")
        n, h, w, _ = x.shape
        if min(h, w) < self.crop:
            raise NrtError(f"FID crops of {self.crop} pixels do not fit images of {h}x{w}: "
                           "choose a smaller crop (the same for every set you compare).")
        if self.white is not None:
            x = (log_tonemap(x) / math.log1p(self.white)).clamp(0, 1)
        elif x.min() < 0 or x.max() > 1:
            raise NrtError("FID without white= takes images in [0, 1]; pass white=<radiance> "
                           "for linear radiance.")
        gen = self._gen[real]
        tops = torch.randint(0, h - self.crop + 1, (n, self.n_crops), generator=gen)
        lefts = torch.randint(0, w - self.crop + 1, (n, self.n_crops), generator=gen)
        out = [x[i, t:t + self.crop, s:s + self.crop]
               for i in range(n) for t, s in zip(tops[i].tolist(), lefts[i].tolist(),
                                                 strict=True)]
        return torch.stack(out).permute(0, 3, 1, 2).contiguous()

    @torch.no_grad()
    def update(self, images: torch.Tensor, real: bool) -> None:
        dev = next(self.inception.parameters()).device
        for chunk in self.crops(images, real).split(self.batch):
            feats = self.inception((chunk * 255).to(torch.uint8).to(dev))
            self._features[real].append(feats.double().cpu())

    def compute(self) -> torch.Tensor:
        if min(self.count(True), self.count(False)) < 2:
            raise NrtError(f"FID needs at least 2 crops of each set, has {self.count(True)} "
                           f"real and {self.count(False)} generated.")
        return frechet_distance(torch.cat(self._features[True]),
                                torch.cat(self._features[False])).float()


def density_agreement(pred: torch.Tensor, ref: torch.Tensor) -> dict[str, torch.Tensor]:
    """Pearson correlation and relative L2 error ``|pred - ref| / |ref|`` of two fields."""
    p, r = pred.flatten().double(), ref.flatten().double()
    pc, rc = p - p.mean(), r - r.mean()
    corr = (pc @ rc) / (pc.norm() * rc.norm()).clamp_min(1e-30)
    rel = (p - r).norm() / r.norm().clamp_min(1e-30)
    return {"corr": corr.float(), "rel_err": rel.float()}


def property_mse(pred: dict[str, torch.Tensor], ref: dict[str, torch.Tensor],
                 with_g: bool = True) -> dict[str, torch.Tensor]:
    """MSE x 10^2 (the paper's unit) of sigma_a, sigma_s, sigma_t (over cells and RGB) and,
    when ``with_g``, of g weighted by the reference sigma_s (its channel mean, normalised),
    between grids of the same layout (``sigma_a``, ``sigma_s`` (..., 3), ``g`` (...))."""
    out = {}
    for key in ("sigma_a", "sigma_s"):
        out[key] = torch.mean((pred[key].double() - ref[key].double()) ** 2)
    sigma_t = (pred["sigma_a"] + pred["sigma_s"]).double()
    out["sigma_t"] = torch.mean((sigma_t - (ref["sigma_a"] + ref["sigma_s"]).double()) ** 2)
    if with_g:
        weight = ref["sigma_s"].double().mean(-1)
        err = (pred["g"].double() - ref["g"].double()) ** 2
        out["g"] = (weight * err).sum() / weight.sum().clamp_min(1e-30)
    return {k: (100 * v).float() for k, v in out.items()}
