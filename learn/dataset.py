"""Episodes on disk -> features, a split by episode, rotation augmentation, and graph sets for batched training."""
from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from data_schema.episode import read_episode
from learn import frames
from learn.features import BEAM_POINTS, JOINT_POINTS, EpisodeFeatures, extract
from learn.graph import BEAM, JOINT, GraphIndex, disjoint_union
from learn.model import Static
from learn.packs import pack_dir, pack_paths, packed, read_pack
from learn.symmetry import rotation_angles, rotation_z

SPLITS = ("train", "val", "test")
FIT_BLOCK = 1024  # training copies per block of the PCA and normaliser fits (Simulator.fit_blocks): ~0.3 GB


def episode_paths(data_dir: str | Path) -> list[Path]:
    """Every episode of a data directory: its episode files (*.h5) and the episodes its feature packs hold
    (learn.packs: <data_dir>/features/*.h5), as <data_dir>/<name> in name order (a packed one's file may not exist:
    load_features reads it from its pack)."""
    files = {p.name: p for p in Path(data_dir).glob("*.h5")}
    names = sorted(files.keys() | packed(data_dir).keys())
    if not names:
        raise FileNotFoundError(f"no episodes (*.h5, or feature packs in {pack_dir(data_dir)}) in {data_dir}; "
                                "generate them with `make dataset`")
    return [Path(data_dir) / n for n in names]


def has_episode(data_dir: str | Path, name: str) -> bool:
    """Is episode `name` in data_dir: its file, or its features in one of the directory's packs?"""
    return (Path(data_dir) / name).is_file() or name in packed(data_dir)


def extra_dirs_checked(dirs, key: str = "train_extra_dirs", example: str = "make large-data") -> list[Path]:
    """conf/train.yaml train_extra_dirs / val_extra_dirs (`key`): a list of directories that exist (checked before any
    episode is read)."""
    if dirs is None:
        return []
    if isinstance(dirs, (str, Path)) or not all(isinstance(d, (str, Path)) for d in dirs):
        raise ValueError(f"{key}={dirs!r}: must be a list of directories, e.g. '[data/ds_large]'")
    missing = [str(d) for d in dirs if not Path(d).is_dir()]
    if missing:
        raise FileNotFoundError(f"{key}: {missing} not found (generate them first, e.g. {example})")
    return [Path(d) for d in dirs]


def design_paths(names: list[str], data_dir: str | Path, config: dict | None = None) -> list[Path]:
    """Where the named episodes of a checkpoint's split are: in data_dir, or else in the train_extra_dirs of the
    checkpoint's config (training designs read from other directories: learn.train.extra_designs); a name in
    neither is left at data_dir, whose reader then names the missing file."""
    extra = [Path(d) for d in (config or {}).get("train_extra_dirs") or []]
    out = []
    for n in names:
        found = [d / n for d in extra if has_episode(d, n)] if not has_episode(data_dir, n) else []
        out.append(found[0] if found else Path(data_dir) / n)
    return out


def load_features(paths: list[Path]) -> list[EpisodeFeatures]:
    """Features of each episode path: extracted from its file where there is one (the source of truth), else read
    from the packs of its directory (learn.packs); a path in neither is an error naming it."""
    paths = [Path(p) for p in paths]
    holders = {}
    for p in paths:
        if not p.is_file() and pack_paths(p.parent):
            holders[p] = packed(p.parent).get(p.name)
            if holders[p] is None:
                raise FileNotFoundError(f"{p}: no such episode file, and not in the feature packs of {p.parent} "
                                        f"({', '.join(q.name for q in pack_paths(p.parent))})")
    from_packs = {h: read_pack(h) for h in dict.fromkeys(holders.values())}  # each pack read once
    return [from_packs[holders[p]][p.name] if p in holders else extract(read_episode(p), name=p.name)
            for p in paths]  # read_episode names a missing file


def split_names(features: list[EpisodeFeatures], fractions: dict, seed: int) -> dict[str, list[str]]:
    """Split by episode (never by frame or rotation), shuffled within each design family so that every family
    (random, regular, ...) reaches every split in proportion. Every split with a positive fraction gets >= 1
    episode when there are enough."""
    rng = np.random.default_rng(seed)
    out: dict[str, list[str]] = {s: [] for s in SPLITS}
    fr = np.array([float(fractions[s]) for s in SPLITS])
    fr = fr / fr.sum()
    by_family: dict[str, list[str]] = {}
    for f in features:
        by_family.setdefault(f.family, []).append(f.name)
    for family in sorted(by_family):
        names = sorted(by_family[family])
        names = [names[i] for i in rng.permutation(len(names))]
        n_val = int(round(fr[1] * len(names)))
        n_test = int(round(fr[2] * len(names)))
        out["val"] += names[:n_val]
        out["test"] += names[n_val:n_val + n_test]
        out["train"] += names[n_val + n_test:]
    for s in ("val", "test"):  # a positive fraction never leaves a split empty
        if fr[SPLITS.index(s)] > 0 and not out[s] and len(out["train"]) > 1:
            out[s].append(out["train"].pop())
    return out


SPLIT_MISSING = ("error", "drop")  # what extend_split does with listed episodes the data lacks


def split_missing_checked(value) -> str:
    """conf/train.yaml split_missing: one of SPLIT_MISSING, else an error naming the key."""
    if value not in SPLIT_MISSING:
        raise ValueError(f"split_missing={value!r}: must be {' | '.join(SPLIT_MISSING)} (held-out episodes of "
                         "split_from that the data lack: an error, or left out)")
    return value


def extend_split(split: dict[str, list[str]], names: Iterable[str], missing: str = "error") -> dict[str, list[str]]:
    """An earlier run's split (or a split file's) with the data's episode `names` it does not list added to train:
    a grown dataset keeps its held-out designs, so runs on the old and the new data are evaluated on the same ones.
    Episodes of the old split that are gone are an error, or with missing="drop" left out (the first N episodes of a
    dataset still being generated, held out as the pinned split holds them out)."""
    split_missing_checked(missing)
    names = set(names)
    gone = sorted(n for s in SPLITS for n in split.get(s, []) if n not in names)
    if gone and missing == "error":
        raise FileNotFoundError(f"split_from lists episodes that are not in the data: {gone[:5]} (split_missing=drop "
                                "leaves them out)")
    out = {s: [n for n in split.get(s, []) if n in names] for s in SPLITS}
    out["train"] += sorted(names - {n for s in SPLITS for n in out[s]})
    return out


LATTICE_TURNS = (1, 2, 4)  # labellings per design: as sampled; + from the opposite corner; + the two next corners


def lattice_turned(f: EpisodeFeatures, turns: int) -> list[EpisodeFeatures]:
    """The design labelled from `turns` corners of its lattice (1: as it is; 2: + EpisodeFeatures.half_turned; 4: +
    both quarter turns): the same design, nothing moved, each labelling one the factory gives some sampled design."""
    if turns not in LATTICE_TURNS:
        raise ValueError(f"lattice_turns={turns!r}: must be one of {list(LATTICE_TURNS)} (1 = the design as labelled)")
    if turns == 1:
        return [f]
    h = f.half_turned()
    if turns == 2:
        return [f, h]
    return [f, f.quarter_turned(), h, h.quarter_turned()]


def labelled(features: list[EpisodeFeatures], mirror: bool = False, lattice_turns: int = 1) -> list[EpisodeFeatures]:
    """Each episode labelled from `lattice_turns` corners of its lattice (lattice_turned), with mirror each of those
    also as its mirror image (EpisodeFeatures.mirrored): the copies augment turns."""
    features = [g for f in features for g in lattice_turned(f, lattice_turns)]
    return [g for f in features for g in ((f, f.mirrored()) if mirror else (f,))]


def augment_angles(n: int, rotations: int, seed: int) -> np.ndarray:
    """[n, rotations] the angles about z augment turns each of n copies by: spread over a full turn, with a random
    offset per copy drawn in order from `seed`."""
    rng = np.random.default_rng(seed)
    return np.stack([rotation_angles(rotations, rng) for _ in range(n)]) if n else np.zeros((0, rotations))


def augment(features: list[EpisodeFeatures], rotations: int, seed: int, mirror: bool = False,
            lattice_turns: int = 1) -> list[EpisodeFeatures]:
    """The labelled copies of each episode (labelled: lattice corners, mirror), all rotated about z (through the
    fixed joint) by `rotations` angles spread over a full turn, with a random offset per copy (augment_angles);
    rotations <= 1 keeps them as they are."""
    features = labelled(features, mirror, lattice_turns)
    if rotations <= 1:
        return features
    angles = augment_angles(len(features), rotations, seed)
    return [f.rotated(rotation_z(a)) for f, row in zip(features, angles) for a in row]


@dataclass
class GraphSet:
    """Several episodes as one disjoint graph; states [F, J, Dj] / [F, B, Db] (all items share the frame times)."""

    items: list[EpisodeFeatures]
    t: torch.Tensor  # [F]
    joint_state: torch.Tensor  # [F, J, Dj]
    beam_state: torch.Tensor  # [F, B, Db]
    static: Static
    joint_offsets: np.ndarray  # [n_items + 1]
    beam_offsets: np.ndarray  # [n_items + 1]

    @classmethod
    def build(cls, items: list[EpisodeFeatures]) -> "GraphSet":
        t = items[0].t
        for f in items:
            if f.t.shape != t.shape or not np.allclose(f.t, t):
                raise ValueError(f"episode {f.name} has frame times {f.t.tolist()}, {items[0].name} has {t.tolist()}; "
                                 "a graph set needs episodes saved at the same frames")
        inc, jo, bo = disjoint_union([f.incidence for f in items])
        cat = lambda arrays: torch.as_tensor(np.concatenate(arrays, axis=-2), dtype=torch.float32)  # noqa: E731
        return cls(items=items, t=torch.as_tensor(t, dtype=torch.float32),
                   joint_state=cat([f.joint_state for f in items]), beam_state=cat([f.beam_state for f in items]),
                   static=Static(cat([f.joint_bc for f in items]), cat([f.beam_bc for f in items]),
                                 inc.tensors()),
                   joint_offsets=jo, beam_offsets=bo)

    @classmethod
    def first_frames(cls, items: list[EpisodeFeatures]) -> "GraphSet":
        """The set of the items' frame 0 only (whatever their frame times): what a rollout starts from."""
        if not items:
            raise ValueError("a graph set needs at least one design")
        return cls.build([f.first_frame() for f in items])

    @property
    def index(self) -> GraphIndex:
        return self.static.index

    def part(self, x: torch.Tensor, i: int, block) -> torch.Tensor:
        """[..., N, D] rows of the whole set -> item i's rows (block JOINT or BEAM)."""
        o = self.joint_offsets if block is JOINT else self.beam_offsets
        return x[..., int(o[i]):int(o[i + 1]), :]

    def points_of(self, points: torch.Tensor, i: int) -> torch.Tensor:
        """[..., P, 3] rebuild_all_points of the whole set (every joint's points, then every beam's) -> item i's, in
        its point_nodes order."""
        pj, pb = len(JOINT_POINTS), len(BEAM_POINTS)
        jo, bo, beams_from = self.joint_offsets, self.beam_offsets, int(self.joint_offsets[-1]) * pj
        return torch.cat([points[..., int(jo[i]) * pj:int(jo[i + 1]) * pj, :],
                          points[..., beams_from + int(bo[i]) * pb:beams_from + int(bo[i + 1]) * pb, :]], -2)

    def __len__(self) -> int:
        return len(self.items)

    def batches(self, batch_size: int | None, generator: torch.Generator, rotations: int = 1) -> Iterable["GraphSet"]:
        """Shuffled mini-batches of items (batch_size None or <= 0: the whole set, batch gradient descent), built one
        at a time as they are iterated (the order and angles are drawn at the call).
        rotations > 1: every item `rotations` times, the copies turned about z by angles spread over a turn from a
        random offset per item, drawn from `generator`: new angles at every call (augment draws them once)."""
        n = len(self.items)
        copies = max(int(rotations), 1)
        whole = not batch_size or batch_size <= 0 or batch_size >= n * copies
        if whole and copies == 1:
            return [self]
        batch_size = n * copies if whole else batch_size
        order = torch.randperm(n * copies, generator=generator).tolist()
        if copies == 1:
            return (GraphSet.build([self.items[i] for i in order[s:s + batch_size]]) for s in range(0, n, batch_size))
        offsets = torch.rand(n, generator=generator, dtype=torch.float64).numpy() * 2.0 * np.pi / copies
        return turned_batches(self.items, order, batch_size,  # copy c: item c % n, its (c // n)-th angle
                              lambda c: (c % n, offsets[c % n] + 2.0 * np.pi * (c // n) / copies))

    def rotated(self, angles) -> "GraphSet":
        """Every item turned about z (through its fixed joint, the features' origin) by its own angle: states and
        boundary-condition terms as EpisodeFeatures.rotated turns them (points and vectors R v, stresses R s R^T),
        computed on the stacked tensors."""
        if len(angles) != len(self):
            raise ValueError(f"{len(angles)} angles for {len(self)} items")
        a = torch.as_tensor(np.asarray(angles, dtype=np.float64))
        c, s, zero, one = torch.cos(a), torch.sin(a), torch.zeros_like(a), torch.ones_like(a)
        R = torch.stack([torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1),
                         torch.stack([zero, zero, one], -1)], -2).to(torch.float32)  # [n, 3, 3]
        out = {}
        for name, block, offsets in (("joint", JOINT, self.joint_offsets), ("beam", BEAM, self.beam_offsets)):
            Rn = R[torch.as_tensor(np.repeat(np.arange(len(self)), np.diff(offsets)))]  # [nodes, 3, 3]
            out[name] = frames.rotate_state(getattr(self, f"{name}_state"), block, Rn, to_local=False)  # every frame
            bc = getattr(self.static, f"{name}_bc").clone()
            for sl in block.bc.slices("point") + block.bc.slices("vector"):
                bc[:, sl] = frames.rotate_vectors(bc[:, sl], Rn, to_local=False)
            out[f"{name}_bc"] = bc
        return GraphSet(items=self.items, t=self.t, joint_state=out["joint"], beam_state=out["beam"],
                        static=Static(out["joint_bc"], out["beam_bc"], self.static.index),
                        joint_offsets=self.joint_offsets, beam_offsets=self.beam_offsets)

    def turned_copies(self, angles: np.ndarray, items: slice = slice(None)) -> "GraphSet":
        """[n, R] angles -> one set of every item (or of the items[items]) turned by each of its R angles,
        item-major (the order augment gives): what a TurnedSet trains on, held in memory at once."""
        chosen, angles = self.items[items], angles[items]
        return GraphSet.build([f for f in chosen for _ in range(angles.shape[1])]).rotated(angles.ravel())

    def fit_blocks(self, size: int = FIT_BLOCK) -> Callable[[], Iterator[tuple]]:
        """What Simulator.fit_blocks fits on: a callable yielding (joint_state, beam_state, static) of `size` items
        at a time, so the fit's terms are never built for the whole set at once."""
        def blocks():
            for start in range(0, len(self), size):
                part = GraphSet.build(self.items[start:start + size])
                yield part.joint_state, part.beam_state, part.static
        return blocks


def turned_batches(items: list[EpisodeFeatures], order: list[int], batch_size: int,
                   copy) -> Iterator[GraphSet]:
    """Mini-batches of the copies `order` lists, `batch_size` at a time, each built only when it is reached (an
    epoch never holds more than one): copy k is items[i] turned about z by angle a, (i, a) = copy(k)."""
    for start in range(0, len(order), batch_size):
        pairs = [copy(k) for k in order[start:start + batch_size]]
        yield GraphSet.build([items[i] for i, _ in pairs]).rotated([a for _, a in pairs])


@dataclass
class TurnedSet:
    """A training set that turns its copies about z per batch instead of holding them: item i of `base` in each of
    its angles[i] (drawn once, augment_angles). Its batches are the stored set's, augment(..., rotations=R) built as
    one GraphSet, item for item and in the same shuffled order, to float32 round-off; it holds 1/R of the memory and
    pays a rotation per batch (conf/train.yaml rotations_stored=false)."""

    base: GraphSet
    angles: np.ndarray  # [n items, R]

    def __len__(self) -> int:
        return self.angles.size

    def batches(self, batch_size: int | None, generator: torch.Generator, rotations: int = 1) -> Iterable[GraphSet]:
        """As GraphSet.batches, each copy turned by its own fixed angle; the order is drawn at the call."""
        if rotations > 1:
            raise ValueError("a TurnedSet has its angles; new angles per epoch (rotations_redraw) turn the base set")
        n, R = self.angles.shape
        total = n * R
        if not batch_size or batch_size <= 0 or batch_size >= total:
            return [self.base.turned_copies(self.angles)]
        order = torch.randperm(total, generator=generator).tolist()
        return turned_batches(self.base.items, order, batch_size, lambda k: (k // R, self.angles[k // R, k % R]))

    def fit_blocks(self, size: int = FIT_BLOCK) -> Callable[[], Iterator[tuple]]:
        """As GraphSet.fit_blocks over every turned copy, item-major: the copies of `size` // R items at a time are
        built and turned as the fit reaches them (the stored set's terms, block by block, to float32 round-off)."""
        per = max(size // self.angles.shape[1], 1)

        def blocks():
            for start in range(0, len(self.base), per):
                part = self.base.turned_copies(self.angles, slice(start, start + per))
                yield part.joint_state, part.beam_state, part.static
        return blocks
