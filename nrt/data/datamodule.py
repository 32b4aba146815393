"""Lightning DataModule of camera rays: random jittered batches for training, whole
held-out images for validation. Rays are made on the fly from the dataset tensors
(no per-epoch copies); every batch carries the known background ``E(v)`` of its rays.

A batch is a dict of ``origins``, ``dirs`` (unit view directions v), ``rgb`` (pixel
radiance) and ``background`` (``E(v)`` of the ray's environment), each (B, 3);
validation batches add ``view`` (index) and ``shape`` (H, W).
"""

from __future__ import annotations

import lightning as L
import torch
from torch.utils.data import DataLoader, IterableDataset

from nrt.cameras import camera_rays
from nrt.data.dataset import SceneDataset, load_dataset
from nrt.errors import DatasetError
from nrt.physics.envmap import EnvironmentMap


def environment_radiance(data: SceneDataset, env_index: torch.Tensor, dirs: torch.Tensor
                         ) -> torch.Tensor:
    """``E(v)`` (B, 3) of each ray's environment along its view direction ``dirs`` (B, 3)."""
    out = torch.empty_like(dirs)
    for e, envmap in enumerate(data.envmaps):
        mask = env_index == e
        if mask.any():
            out[mask] = envmap.lookup(dirs[mask]).to(dirs.dtype)
    return out


class RandomRays(IterableDataset):
    """``steps`` batches of ``batch_size`` rays drawn uniformly over all pixels of all
    training images, each jittered uniformly inside its pixel (box-filter pixels)."""

    def __init__(self, data: SceneDataset, batch_size: int, steps: int, seed: int):
        self.data, self.batch_size, self.steps, self.seed = data, batch_size, steps, seed
        self.epoch = 0

    def __iter__(self):
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        self.epoch += 1
        n, h, w = self.data.images.shape[:3]
        for _ in range(self.steps):
            flat = torch.randint(0, n * h * w, (self.batch_size,), generator=g)
            img, pix = flat // (h * w), flat % (h * w)
            row, col = pix // w, pix % w
            jitter = torch.rand(self.batch_size, 2, generator=g)
            o, d = camera_rays(self.data.c2w[img], self.data.intrinsics,
                               col + jitter[:, 0], row + jitter[:, 1])
            env = self.data.env_index[img]
            yield {"origins": o, "dirs": d, "rgb": self.data.images[img, row, col],
                   "background": environment_radiance(self.data, env, d)}


class HeldOutImages(IterableDataset):
    """Whole held-out images, one batch per image, rays through pixel centres."""

    def __init__(self, data: SceneDataset, max_views: int | None):
        self.data = data
        n = len(data)
        k = n if not max_views else min(max_views, n)
        self.views = torch.linspace(0, n - 1, k).round().long().unique().tolist()

    def __len__(self) -> int:
        return len(self.views)

    def __iter__(self):
        h, w = self.data.images.shape[1:3]
        for i in self.views:
            o, d, rgb = self.data.rays(i)
            env = self.data.env_index[i].expand(h * w)
            d = d.reshape(-1, 3)
            yield {"origins": o.reshape(-1, 3), "dirs": d, "rgb": rgb.reshape(-1, 3),
                   "background": environment_radiance(self.data, env, d),
                   "view": i, "shape": (h, w)}


class RayDataModule(L.LightningDataModule):
    """Training rays from ``transforms_train.json``, validation on ``transforms_test.json``,
    optionally only the frames lit by ``environments`` (names or positions)."""

    def __init__(self, dataset_dir: str, batch_size: int = 4096, steps_per_epoch: int = 500,
                 val_views: int | None = None, seed: int = 0,
                 environments: list[str | int] | None = None):
        super().__init__()
        self.dataset_dir, self.environments = dataset_dir, environments
        self.batch_size, self.steps_per_epoch = batch_size, steps_per_epoch
        self.val_views, self.seed = val_views, seed
        self.train_data: SceneDataset | None = None
        self.val_data: SceneDataset | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_data is None:
            self.train_data = load_dataset(self.dataset_dir, "train")
            self.val_data = load_dataset(self.dataset_dir, "test")
            if self.environments is not None:
                self.train_data = self.train_data.select_environments(list(self.environments))
                self.val_data = self.val_data.select_environments(list(self.environments))

    @property
    def environment(self) -> EnvironmentMap:
        """The one environment lighting the selected frames (stage 2 learns one light field)."""
        self.setup()
        used = self.train_data.env_index.unique().tolist()
        if len(used) != 1:
            names = [self.train_data.env_names[i] for i in used]
            raise DatasetError(f"Dataset '{self.dataset_dir}': this stage learns the light field "
                               f"of one environment, but the training frames use {names}; "
                               "choose one with data.environments=[<name or position>].")
        return self.train_data.envmaps[used[0]]

    @property
    def bbox(self) -> torch.Tensor:
        self.setup()
        return self.train_data.bbox

    @property
    def ground_truth(self) -> dict[str, torch.Tensor] | None:
        self.setup()
        return self.train_data.ground_truth

    def train_dataloader(self) -> DataLoader:
        return DataLoader(RandomRays(self.train_data, self.batch_size, self.steps_per_epoch,
                                     self.seed), batch_size=None)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(HeldOutImages(self.val_data, self.val_views), batch_size=None)
