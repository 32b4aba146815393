"""Families of procedural scenes (``scene=family``): K members drawn from seeds under one
shared training environment, with a second environment held back for novel illumination
(the paper's single-illumination generative variant).

Member ``i`` is the family's scene config with ``seed = scene.seed + i``, named
``<name>_seed<seed>``, lit by exactly two procedural skies: ``scene.family.train_sky``
(environment 0, the one stages train on) and ``scene.family.heldout_sky`` (environment 1).
Everything else (medium generator, effects, cameras, spp, sizes) is the scene's, so the
members share one camera rig. Each member is an ordinary dataset in the cache
(``<data_root>/<member name>-<spec hash>/``, docs/data_format.md): rendered once, reused
by every family that holds the same spec, readable by every tool that reads a dataset.

The family folder ``<data_root>/<name>-<family hash>/`` holds only the manifest
``family.json`` (written once every member is complete; the hash covers the members' spec
hashes and the environment roles)::

    {"format_version": 1, "name": "family", "hash": "...",
     "environments": {"train": "sky0", "heldout": "sky1"},
     "members": [{"index": 0, "seed": 0, "name": "family_seed0",
                  "folder": "../family_seed0-<spec hash>", "spec_hash": "...",
                  "environments": {"train": "sky0", "heldout": "sky1"}}, ...]}

Member folders are relative to the family folder. :func:`load_family` reads it back:
``family.members`` (all), ``family.member(i)``.
"""

from __future__ import annotations

import copy
import json
import logging
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from nrt.data.render import dataset_folder, ensure_rendered, is_rendered
from nrt.data.spec import resolve_scene, spec_hash
from nrt.errors import DatasetError, SceneError
from nrt.files import check_name, write_text_atomic, writing

log = logging.getLogger(__name__)

FAMILY_FILE = "family.json"
FAMILY_FORMAT_VERSION = 1


@dataclass(frozen=True)
class FamilyMember:
    """One scene of a family: its position, seed, name, dataset folder (absolute) and
    environment roles ``{"train": name, "heldout": name}``."""

    index: int
    seed: int
    name: str
    folder: Path
    environments: dict[str, str]


@dataclass(frozen=True)
class Family:
    """A rendered family read from its folder: ``members`` in order (``member(i)`` for
    one), the shared training environment and the held-back one (names in every member's
    ``transforms_*.json``)."""

    root: Path
    name: str
    train_environment: str
    heldout_environment: str
    members: tuple[FamilyMember, ...]

    def __len__(self) -> int:
        return len(self.members)

    def member(self, index: int) -> FamilyMember:
        """Member ``index`` (0 <= index < K)."""
        if not 0 <= index < len(self.members):
            raise DatasetError(f"Family '{self.root}' has members 0..{len(self.members) - 1}; "
                               f"there is no member {index}.")
        return self.members[index]

    def folders(self) -> list[Path]:
        """Every member's dataset folder, in member order."""
        return [m.folder for m in self.members]


def _fail(key: str, message: str) -> SceneError:
    return SceneError(f"Scene key 'scene.{key}': {message}")


def _sky_seed(family: Mapping, key: str) -> int:
    value = family.get(key)
    if value is None:
        what = ("a second environment held back for novel illumination"
                if key == "heldout_sky" else "one shared training environment")
        raise _fail(f"family.{key}", f"a family needs {what}: give the seed of a procedural "
                    "sky (the family's two skies must differ).")
    if not isinstance(value, int) or isinstance(value, bool):
        raise _fail(f"family.{key}", f"must be a whole number (a sky seed), got {value!r}.")
    return value


def member_scenes(scene_cfg: Mapping) -> list[dict]:
    """The scene configs of a family's members (``scene_cfg`` holds ``family``), checked
    before anything is rendered: K >= 1, two different skies, media drawn from seeds."""
    family = scene_cfg["family"]
    k = family.get("members")
    if not isinstance(k, int) or isinstance(k, bool) or k < 1:
        raise _fail("family.members", f"the number of members K must be a whole number "
                    f">= 1, got {k!r}. The preset sets it as budget.family.members (tiny 4, "
                    "cpu 16, paper 50); override either key.")
    train, heldout = _sky_seed(family, "train_sky"), _sky_seed(family, "heldout_sky")
    if train == heldout:
        raise _fail("family.heldout_sky", f"= {heldout} is also the training sky: the "
                    "held-back environment must differ from the shared training one.")
    if scene_cfg.get("path"):
        raise _fail("path", "a family renders its members from seeds; scene.path (one "
                    "existing dataset) cannot be a family. Set scene.path=null.")
    if scene_cfg["medium"].get("elements"):
        raise _fail("medium.elements", "a family draws each member's medium from its seed; "
                    "an explicit elements list would give K identical media. Set "
                    "scene.medium.elements=null.")
    if (scene_cfg.get("environments") or {}).get("files"):
        raise _fail("environments.files", "a family is lit by its two procedural skies "
                    "(scene.family.train_sky, scene.family.heldout_sky); environment files "
                    "are not supported for families.")
    base = {key: value for key, value in scene_cfg.items() if key != "family"}
    members = []
    for i in range(k):
        member = copy.deepcopy(base)
        member["seed"] = int(scene_cfg["seed"]) + i
        member["name"] = f"{scene_cfg['name']}_seed{member['seed']}"
        member["environments"] = {**member["environments"], "sky_seeds": [train, heldout],
                                  "files": {}}
        members.append(member)
    return members


def unseen_member_scenes(scene_cfg: Mapping, count: int, start: int = 0) -> list[dict]:
    """The scene configs of ``count`` media the family's generator draws after its K
    members and ``start`` more (seeds ``scene.seed + K + start`` onward, named as members
    are): new media of the family that no run trained on, for scoring a generator against
    the family itself; ``start`` = j * count gives the j-th of disjoint sets."""
    if start < 0 or count < 0:
        raise ValueError(f"unseen members: count ({count}) and start ({start}) must be >= 0")
    first = int(scene_cfg["family"]["members"]) + int(start)
    wider = {**scene_cfg, "family": {**scene_cfg["family"], "members": first + count}}
    return member_scenes(wider)[first:]


def _manifest(name: str, specs: list[dict], data_root: Path) -> dict:
    """The manifest of a family of resolved member ``specs`` (its hash included)."""
    train, heldout = list(specs[0]["environments"])
    roles = {"train": train, "heldout": heldout}
    hashes = [spec_hash(spec) for spec in specs]
    family_hash = spec_hash({"name": name, "environments": roles, "members": hashes})
    members = [{"index": i, "seed": spec["seed"], "name": spec["name"],
                "folder": os.path.relpath(dataset_folder(spec, data_root),
                                          data_root / f"{name}-{family_hash}"),
                "spec_hash": h, "environments": dict(roles)}
               for i, (spec, h) in enumerate(zip(specs, hashes, strict=True))]
    return {"format_version": FAMILY_FORMAT_VERSION, "name": name, "hash": family_hash,
            "environments": roles, "members": members}


def ensure_family(scene_cfg: Mapping, data_root: str | Path, variant: str = "auto",
                  progress: bool = True) -> Path:
    """The folder of the family ``scene_cfg`` describes, rendering the members missing from
    the dataset cache (every member is checked before the first is rendered) and writing
    ``family.json`` once all are complete. A progress bar counts members."""
    data_root = Path(data_root)
    check_name("scene.name", scene_cfg["name"], SceneError)
    specs = [resolve_scene(member) for member in member_scenes(scene_cfg)]
    manifest = _manifest(str(scene_cfg["name"]), specs, data_root)
    folder = data_root / f"{manifest['name']}-{manifest['hash']}"
    missing = sum(not is_rendered(spec, data_root) for spec in specs)
    start = time.perf_counter()
    bar = tqdm(specs, desc=f"family {manifest['name']}", unit="scene", disable=not progress)
    for spec in bar:
        ensure_rendered(spec, data_root, variant=variant, progress=progress)
    bar.close()
    if not (folder / FAMILY_FILE).is_file():
        with writing("the family folder", folder):
            folder.mkdir(parents=True, exist_ok=True)
        write_text_atomic(folder / FAMILY_FILE, json.dumps(manifest, indent=1),
                          "the family record")
    log.info("Family '%s' of %d members: %d rendered in %.1f s, %d reused from the cache: %s",
             manifest["name"], len(specs), missing, time.perf_counter() - start,
             len(specs) - missing, folder)
    return folder


def load_family(folder: str | Path) -> Family:
    """Read the family folder written by :func:`ensure_family` (member folders resolved
    and checked to exist)."""
    root = Path(folder).expanduser()
    path = root / FAMILY_FILE
    if not path.is_file():
        raise DatasetError(f"Family folder '{root}' has no {FAMILY_FILE}. Render the family "
                           "with `nrt-data scene=family` (it prints the folder).")
    try:
        data = json.loads(path.read_text())
        members = tuple(FamilyMember(index=int(m["index"]), seed=int(m["seed"]),
                                     name=str(m["name"]), folder=(root / m["folder"]).resolve(),
                                     environments=dict(m["environments"]))
                        for m in data["members"])
        family = Family(root=root, name=str(data["name"]),
                        train_environment=str(data["environments"]["train"]),
                        heldout_environment=str(data["environments"]["heldout"]),
                        members=members)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"Family file '{path}' is malformed ({exc!r}). Delete the folder "
                           "and render the family again.") from exc
    for member in members:
        if not member.folder.is_dir():
            raise DatasetError(f"Family file '{path}': member {member.index} "
                               f"('{member.name}') points at '{member.folder}', which does "
                               "not exist. Render the family again (`nrt-data scene=family`).")
    return family
