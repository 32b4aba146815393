"""Lightning DataModules of camera rays: random jittered batches for training, whole
held-out images for validation. Rays are made on the fly from the dataset tensors
(no per-epoch copies); every batch carries the known background ``E(v)`` of its rays.

A batch is a dict of ``origins``, ``dirs`` (unit view directions v), ``rgb`` (pixel
radiance) and ``background`` (``E(v)`` of the ray's environment), each (B, 3), and
``env`` (B,), the position of each ray's environment in the dataset's; validation batches
add ``view`` (index) and ``shape`` (H, W), and their ``env`` is one int. :class:`RayDataModule`
reads one dataset; :class:`FamilyRayDataModule` the members of a scene family
(``mode=generative``), whose batches add ``member`` (B,) (training: each ray's member;
validation: the view's member, and ``view`` counts within it). With ``twins`` > 0 the first
``twins`` rays of a training batch each get a second ray through the same pixel, jittered
independently: ``twin_origins``, ``twin_dirs``, ``twin_background`` (twins, 3), for an
unbiased estimate of the squared error of a box-filtered pixel (nrt/losses/photo.py).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader, IterableDataset

from nrt.cameras import camera_rays
from nrt.data.dataset import SceneDataset, load_dataset
from nrt.data.family import Family, load_family
from nrt.distributed import rank_seed
from nrt.errors import ConfigError, DatasetError
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
    training images, each jittered uniformly inside its pixel (box-filter pixels).
    ``members`` (N,): the family member of each image; batches then carry ``member``.
    ``members_per_step`` M (with ``members``): each batch draws M of the K members first
    (from a generator of ``member_seed``, the same on every rank), then each ray a member
    among them uniformly, an image of it and a pixel; the batch carries them sorted as
    ``step_members`` (M,). ``twins``: how many of a batch's first rays get a twin through
    the same pixel, its jitter drawn from a generator of its own, so the batches' rays do
    not depend on it."""

    def __init__(self, data: SceneDataset, batch_size: int, steps: int, seed: int,
                 members: torch.Tensor | None = None, twins: int = 0,
                 members_per_step: int | None = None, member_seed: int = 0):
        self.data, self.batch_size, self.steps, self.seed = data, batch_size, steps, seed
        self.members, self.twins = members, max(0, min(int(twins), batch_size))
        self.epoch, self.skip = 0, 0
        self.frames = None  # (K, F): the images of each member, when a step draws members
        if members is not None and members_per_step:
            self.frames = torch.stack([torch.nonzero(members == k).flatten()
                                       for k in range(int(members.max()) + 1)])
            self.members_per_step, self.member_seed = int(members_per_step), member_seed

    def draw(self, g: torch.Generator, g_members: torch.Generator | None
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """One batch's images and pixels (flat in the image), and its members (None when
        every member may appear)."""
        n, h, w = self.data.images.shape[:3]
        if self.frames is None:
            flat = torch.randint(0, n * h * w, (self.batch_size,), generator=g)
            return flat // (h * w), flat % (h * w), None
        k, f = self.frames.shape
        step = torch.randperm(k, generator=g_members)[:self.members_per_step].sort().values
        slot = torch.randint(0, len(step), (self.batch_size,), generator=g)
        frame = torch.randint(0, f, (self.batch_size,), generator=g)
        pix = torch.randint(0, h * w, (self.batch_size,), generator=g)
        return self.frames[step[slot], frame], pix, step

    def resume_at(self, epoch: int, batches_done: int) -> None:
        """Continue a resumed run in ``epoch`` after its first ``batches_done`` batches: the
        next pass yields the rest of that epoch (nothing when it is complete), the batches
        a run left alone draws."""
        self.epoch, self.skip = int(epoch), max(0, int(batches_done))

    def __iter__(self):
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        g_twin = torch.Generator().manual_seed((self.seed * 1_000_003 + self.epoch) ^ (1 << 40))
        g_members = None if self.frames is None else torch.Generator().manual_seed(
            (self.member_seed * 1_000_003 + self.epoch) ^ (1 << 41))
        self.epoch += 1
        skip, self.skip = self.skip, 0
        w = self.data.images.shape[2]
        for i in range(self.steps):
            img, pix, step = self.draw(g, g_members)
            jitter = torch.rand(self.batch_size, 2, generator=g)
            if i < skip:  # drawn and dropped: the generators stay on the run's course
                if self.twins:
                    torch.rand(self.twins, 2, generator=g_twin)
                continue
            row, col = pix // w, pix % w
            o, d = camera_rays(self.data.c2w[img], self.data.intrinsics,
                               col + jitter[:, 0], row + jitter[:, 1])
            env = self.data.env_index[img]
            batch = {"origins": o, "dirs": d, "rgb": self.data.images[img, row, col],
                     "background": environment_radiance(self.data, env, d), "env": env}
            if self.members is not None:
                batch["member"] = self.members[img]
            if step is not None:
                batch["step_members"] = step
            if self.twins:
                k = self.twins
                jitter = torch.rand(k, 2, generator=g_twin)
                o, d = camera_rays(self.data.c2w[img[:k]], self.data.intrinsics,
                                   col[:k] + jitter[:, 0], row[:k] + jitter[:, 1])
                batch |= {"twin_origins": o, "twin_dirs": d,
                          "twin_background": environment_radiance(self.data, env[:k], d)}
            yield batch


def _spread(n: int, max_views: int | None) -> list[int]:
    """Up to ``max_views`` of ``n`` positions, evenly spread (all when ``max_views`` is
    None or 0)."""
    k = n if not max_views else min(max_views, n)
    return torch.linspace(0, n - 1, k).round().long().unique().tolist()


class HeldOutImages(IterableDataset):
    """Whole held-out images, one batch per image, rays through pixel centres. With
    ``members`` (N,), the family member of each image, ``max_views`` applies per member and
    batches carry ``member`` and the view's position within it."""

    def __init__(self, data: SceneDataset, max_views: int | None,
                 members: torch.Tensor | None = None):
        self.data = data
        if members is None:  # (member, view, image)
            self.views = [(None, i, i) for i in _spread(len(data), max_views)]
        else:
            frames = [torch.nonzero(members == k).flatten().tolist()
                      for k in range(int(members.max()) + 1)]
            self.views = [(k, j, own[j]) for k, own in enumerate(frames)
                          for j in _spread(len(own), max_views)]

    def __len__(self) -> int:
        return len(self.views)

    def __iter__(self):
        h, w = self.data.images.shape[1:3]
        for member, view, i in self.views:
            o, d, rgb = self.data.rays(i)
            env = self.data.env_index[i].expand(h * w)
            d = d.reshape(-1, 3)
            batch = {"origins": o.reshape(-1, 3), "dirs": d, "rgb": rgb.reshape(-1, 3),
                     "background": environment_radiance(self.data, env, d),
                     "view": view, "shape": (h, w), "env": int(self.data.env_index[i])}
            if member is not None:
                batch["member"] = member
            yield batch


class RayDataModule(L.LightningDataModule):
    """Training rays from ``transforms_train.json``, validation on ``transforms_test.json``,
    optionally only the frames lit by ``environments`` (names or positions); ``twins``: how
    many of a training batch's first rays get a twin (:class:`RandomRays`)."""

    def __init__(self, dataset_dir: str, batch_size: int = 4096, steps_per_epoch: int = 500,
                 val_views: int | None = None, seed: int = 0,
                 environments: list[str | int] | None = None, twins: int = 0):
        super().__init__()
        self.dataset_dir, self.environments, self.twins = dataset_dir, environments, twins
        self.batch_size, self.steps_per_epoch = batch_size, steps_per_epoch
        self.val_views, self.seed = val_views, seed
        self.train_data: SceneDataset | None = None
        self.val_data: SceneDataset | None = None
        self.train_members: torch.Tensor | None = None  # a family's member of each frame
        self.val_members: torch.Tensor | None = None
        self.members_per_step: int | None = None  # a family's members a step draws from

    def setup(self, stage: str | None = None) -> None:
        if self.train_data is None:
            self.train_data = load_dataset(self.dataset_dir, "train")
            self.val_data = load_dataset(self.dataset_dir, "test")
            if self.environments is not None:
                self.train_data = self.train_data.select_environments(list(self.environments))
                self.val_data = self.val_data.select_environments(list(self.environments))

    def training_environments(self) -> dict[int, EnvironmentMap]:
        """The environments lighting the selected training frames: their positions in the
        dataset's environments (a ray batch's ``env``) -> map, in that order."""
        self.setup()
        used = sorted(self.train_data.env_index.unique().tolist())
        return {i: self.train_data.envmaps[i] for i in used}

    @property
    def bbox(self) -> torch.Tensor:
        self.setup()
        return self.train_data.bbox

    @property
    def ground_truth(self) -> dict[str, torch.Tensor] | None:
        self.setup()
        return self.train_data.ground_truth

    def run_info(self) -> dict:
        """What ``run.json`` records about the data: the dataset folder and the
        environments trained on."""
        self.setup()
        return {"dataset_dir": str(Path(self.dataset_dir).resolve()),
                "environments": self.train_data.environments_used()}

    def train_dataloader(self) -> DataLoader:
        """Random ray batches; a resumed run continues where its checkpoint left them (one
        batch an optimizer step, as every stage takes). In a run of several processes rank
        r draws its own, from :func:`~nrt.distributed.rank_seed` (rank 0 and a one-process
        run from ``seed``), ``batch_size`` rays a step each."""
        trainer = self.trainer
        rank = trainer.global_rank if trainer is not None else 0
        rays = RandomRays(self.train_data, self.batch_size, self.steps_per_epoch,
                          rank_seed(self.seed, rank), self.train_members, self.twins,
                          self.members_per_step, self.seed)
        if trainer is not None and trainer.global_step:
            epoch = trainer.current_epoch
            rays.resume_at(epoch, trainer.global_step - epoch * self.steps_per_epoch)
        return DataLoader(rays, batch_size=None)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(HeldOutImages(self.val_data, self.val_views, self.val_members),
                          batch_size=None)


def merge_members(datasets: list[SceneDataset], root: Path) -> tuple[SceneDataset, torch.Tensor]:
    """One dataset of every frame of ``datasets`` (one split of each family member, in
    member order; they must share image size, intrinsics and medium box) and the member
    of each frame (N,). The members' environments follow one another in the merged
    ``envmaps`` (named ``<member folder>:<name>``); the ground truth stays with the
    members."""
    first = datasets[0]
    for data in datasets[1:]:
        same = (data.images.shape[1:] == first.images.shape[1:]
                and data.intrinsics == first.intrinsics and torch.equal(data.bbox, first.bbox))
        if not same:
            raise DatasetError(f"Family '{root}': member '{data.root}' has other image sizes, "
                               f"intrinsics or medium box than '{first.root}'; the members of "
                               "a family share one camera rig. Render the family again "
                               "(`nrt-data scene=family`).")
    offsets = torch.tensor([0] + [len(d.env_names) for d in datasets[:-1]]).cumsum(0)
    merged = replace(
        first, root=root,
        images=torch.cat([d.images for d in datasets]),
        c2w=torch.cat([d.c2w for d in datasets]),
        env_index=torch.cat([d.env_index + int(o) for d, o in zip(datasets, offsets,
                                                                   strict=True)]),
        env_names=[f"{d.root.name}:{name}" for d in datasets for name in d.env_names],
        envmaps=[m for d in datasets for m in d.envmaps], ground_truth=None, spec=None)
    members = torch.cat([torch.full((len(d),), k, dtype=torch.long)
                         for k, d in enumerate(datasets)])
    return merged, members


class FamilyRayDataModule(RayDataModule):
    """The rays of every member of a scene family (``mode=generative``), under the family's
    shared training environment only: the held-back one is never trained on, nor
    validated on (the EA colour bakes in its lighting).

    Training batches are drawn uniformly over all members' training pixels, so each mixes
    members, and carry each ray's ``member``; validation renders ``val_views`` held-out
    views of each member. With ``members_per_step`` M (null: all K), each training batch
    draws its rays from M of the members only (:class:`RandomRays`), so that a step of
    generative stage 2 decodes M members' media and lights, not K. ``dataset_dir`` is the
    family folder (``family.json``); ``environments`` (names or positions) may name only
    the training environment (``stage.environments: [0]`` in ``conf/mode/generative.yaml``;
    null: the same); the other arguments are :class:`RayDataModule`'s."""

    def __init__(self, dataset_dir: str, members_per_step: int | None = None, **kwargs):
        super().__init__(dataset_dir, **kwargs)
        if members_per_step is not None and (isinstance(members_per_step, bool) or
                                             not isinstance(members_per_step, int) or
                                             members_per_step < 1):
            raise ConfigError(f"data.members_per_step={members_per_step}: a whole number of "
                              "members >= 1, or null for all of them.")
        self.members_per_step = members_per_step
        self.family: Family | None = None
        self.member_ground_truths: list[dict[str, torch.Tensor] | None] = []

    def _training_environment(self, data: SceneDataset) -> str:
        train = self.family.train_environment
        for item in self.environments or []:
            name = data.env_names[item] if isinstance(item, int) and \
                0 <= item < len(data.env_names) else str(item)
            if name != train:
                raise DatasetError(
                    f"Family '{self.dataset_dir}': data.environments names '{item}', but a "
                    f"family trains on its shared training environment '{train}' only (the "
                    f"held-back '{self.family.heldout_environment}' is for novel "
                    "illumination). Set stage.environments=[0] or null.")
        return train

    def setup(self, stage: str | None = None) -> None:
        if self.train_data is not None:
            return
        self.family = load_family(self.dataset_dir)
        splits = {}
        for split in ("train", "test"):
            members = [load_dataset(folder, split) for folder in self.family.folders()]
            env = self._training_environment(members[0])
            members = [data.select_environments([env]) for data in members]
            splits[split] = merge_members(members, self.family.root)
            if split == "train":
                self.member_ground_truths = [data.ground_truth for data in members]
        self.train_data, self.train_members = splits["train"]
        self.val_data, self.val_members = splits["test"]
        counts = torch.bincount(self.train_members).tolist()
        if self.members_per_step is not None and (self.members_per_step > len(counts) or
                                                  len(set(counts)) > 1):
            raise DatasetError(
                f"Family '{self.dataset_dir}': data.members_per_step={self.members_per_step} "
                f"needs at most its {len(counts)} members, each with as many training images "
                f"(they have {counts}); lower it, or set it to null.")

    @property
    def environment(self) -> EnvironmentMap:
        """The family's shared training environment (stage 2 learns its light field). Every
        member holds its own copy; they must agree."""
        self.setup()
        maps = [self.train_data.envmaps[i] for i in self.train_data.env_index.unique().tolist()]
        first = maps[0]
        for envmap in maps[1:]:
            if envmap.radiance.shape != first.radiance.shape or \
                    not torch.allclose(envmap.radiance, first.radiance, rtol=1e-5, atol=0.0):
                raise DatasetError(f"Family '{self.dataset_dir}': the members' training "
                                   f"environments '{self.family.train_environment}' differ; "
                                   "a family shares one training sky. Render the family again "
                                   "(`nrt-data scene=family`).")
        return first

    def training_environments(self) -> dict[int, EnvironmentMap]:
        """The shared training environment alone (:attr:`environment`), under its first
        member's position."""
        return {int(self.train_data.env_index[0]): self.environment}

    @property
    def num_members(self) -> int:
        """K, the family's size."""
        self.setup()
        return len(self.family)

    @property
    def ground_truth(self) -> None:
        """None: a family has one ground truth per member (:attr:`member_ground_truths`)."""
        return None

    def run_info(self) -> dict:
        """What ``run.json`` records about the data: the family folder, its members
        (index, seed, name, dataset folder) and the environment trained on."""
        self.setup()
        return {"family_dir": str(self.family.root.resolve()),
                "members": [{"index": m.index, "seed": m.seed, "name": m.name,
                             "dataset_dir": str(m.folder)} for m in self.family.members],
                "environments": [self.family.train_environment]}
