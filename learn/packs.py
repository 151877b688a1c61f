"""Feature packs: the features of many episodes in one compact HDF5 file, read where the episodes are not.

An episode (data_schema, ~0.9 MB for a 3x3 design) costs the FEA ~18 s on a busy core; what training and
evaluation read of it is learn.features.extract's EpisodeFeatures, ~1/10 of the bytes. A pack holds those features,
exactly (the same float32 / float64 arrays), for the episodes of one data directory, with the generator's manifest
records of them (refusals included, so a refused design is not solved again). `<data_dir>/features/*.h5` are the
packs of a data directory: learn.dataset lists a directory's episodes as its episode files and the names in its
packs, and reads an episode file where there is one (the source of truth), else the pack. So a fresh machine
trains and evaluates on the packs the repository carries (scripts/record.py: `make record-pack` writes them,
`make record-data` puts them in place and solves only what no pack holds).

Layout of a pack (every array concatenated over its episodes, in `names` order; `counts` [n, 5] = frames F,
joints J, beams B, points P, distinct point nodes U of each):
    names [n], meta [n] (JSON: family, design_size, fea_seconds, fea_load_per_cpu, conditions), origin [n, 3],
    t [sum F], beams [sum B, 2], joint_state [sum F*J, Sj], beam_state [sum F*B, Sb], joint_bc [sum J, .],
    beam_bc [sum B, .], point_index [sum P] (into the episode's distinct nodes), nodes [sum U] (FEA node ids),
    node_points [sum F*U, 3] (FEA positions of those nodes, translated like the features), manifest (JSON lines).
Attributes: format, version, layout (the feature layout it was made with, compared on reading).
"""
from __future__ import annotations

import datetime
import functools
import json
import os
from collections.abc import Iterable
from pathlib import Path

import h5py
import numpy as np

from data_schema import atomic
from learn.conditions import PHYSICS_KEYS
from learn.features import BEAM_POINTS, JOINT_POINTS, EpisodeFeatures
from learn.graph import BEAM, JOINT, Incidence

FORMAT = "morphsim.features"
VERSION = 1
PACK_DIR = "features"  # <data_dir>/features/*.h5: the packs of a data directory
# Bump when learn.features.extract computes a field differently with the same layout: packs made before then are
# refused (re-extract them from episodes, or solve them again) instead of mixing two definitions in one training set.
EXTRACT_VERSION = 1
COMPRESSION = dict(compression="gzip", compression_opts=6, shuffle=True)


class PackError(ValueError):
    """A pack that cannot be read as this code's features (another layout or format), or an inconsistent one."""


def layout() -> dict:
    """What a pack's arrays mean: the block terms' field names and sizes, the rebuilt points in order, and the config
    entries its conditions were read from (learn.conditions)."""
    def block(b):
        return {"geometry": b.geometry.names(), "stress": b.stress.names(), "bc": b.bc.names(),
                "state_size": int(b.state_size)}
    return {"extract_version": EXTRACT_VERSION, "joint": block(JOINT), "beam": block(BEAM),
            "joint_points": [p[0] for p in JOINT_POINTS], "beam_points": [p[0] for p in BEAM_POINTS],
            "physics_keys": list(PHYSICS_KEYS)}  # the conditions kept of each episode's config


def pack_dir(data_dir: str | os.PathLike) -> Path:
    return Path(data_dir) / PACK_DIR


def pack_paths(data_dir: str | os.PathLike) -> list[Path]:
    return sorted(pack_dir(data_dir).glob("*.h5"))


def write_pack(path: str | os.PathLike, features: list[EpisodeFeatures], manifest: Iterable[dict] = ()) -> Path:
    """`features` (distinct names) and their manifest records -> the pack at `path`, written atomically. A pack of
    refusals only (no features, some records) keeps those refusals."""
    names = [f.name for f in features]
    manifest = list(manifest)
    if (not names and not manifest) or len(set(names)) != len(names) or not all(names):
        raise PackError(f"write_pack({path}): needs episodes with distinct, non-empty names (or refusals); got "
                        f"{names[:5]}...")
    # every column starts with its empty [0, ...] block: a pack of refusals only has the columns' shapes too
    cols: dict[str, list[np.ndarray]] = {k: [np.zeros((0, *shape), dtype)] for k, shape, dtype in (
        ("t", (), np.float64), ("beams", (2,), np.int64), ("joint_state", (JOINT.state_size,), np.float32),
        ("beam_state", (BEAM.state_size,), np.float32), ("joint_bc", (JOINT.bc.size,), np.float32),
        ("beam_bc", (BEAM.bc.size,), np.float32), ("point_index", (), np.int32), ("nodes", (), np.int64),
        ("node_points", (3,), np.float32))}
    counts, meta, origin = [], [], []
    for f in features:
        F, J, B, P = f.n_frames, f.incidence.n_joints, f.incidence.n_beams, len(f.point_nodes)
        nodes, first, index = np.unique(f.point_nodes, return_index=True, return_inverse=True)
        node_points = f.fea_points[:, first]
        if not np.array_equal(node_points[:, index], f.fea_points):
            raise PackError(f"{f.name}: two rebuilt points of one FEA node have different positions")
        counts.append((F, J, B, P, len(nodes)))
        cols["t"].append(f.t)
        cols["beams"].append(np.stack([f.incidence.senders[:B], f.incidence.receivers[:B]], axis=1))
        cols["joint_state"].append(f.joint_state.reshape(F * J, -1))
        cols["beam_state"].append(f.beam_state.reshape(F * B, -1))
        cols["joint_bc"].append(f.joint_bc)
        cols["beam_bc"].append(f.beam_bc)
        cols["point_index"].append(index.astype(np.int32))
        cols["nodes"].append(nodes)
        cols["node_points"].append(node_points.reshape(-1, 3))
        origin.append(f.origin)
        meta.append(json.dumps({"family": f.family, "design_size": f.design_size, "fea_seconds": f.fea_seconds,
                                "fea_load_per_cpu": f.fea_load_per_cpu, "conditions": f.conditions}))
    with atomic.replacing(path) as tmp, h5py.File(tmp, "w") as h5:
        h5.attrs.update(format=FORMAT, version=VERSION, layout=json.dumps(layout()),
                        created=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"))
        h5.create_dataset("names", data=np.array(names, dtype=object), dtype=h5py.string_dtype())
        h5.create_dataset("meta", data=np.array(meta, dtype=object), dtype=h5py.string_dtype())
        h5.create_dataset("counts", data=np.asarray(counts, np.int64).reshape(-1, 5))
        h5.create_dataset("origin", data=np.asarray(origin, np.float64).reshape(-1, 3))
        for k, parts in cols.items():
            h5.create_dataset(k, data=np.concatenate(parts), **COMPRESSION)
        h5.create_dataset("manifest", data="\n".join(json.dumps(r, sort_keys=True) for r in manifest),
                          dtype=h5py.string_dtype())
    return Path(path)


def _checked(h5: h5py.File, path: Path) -> None:
    if h5.attrs.get("format") != FORMAT or int(h5.attrs.get("version", -1)) != VERSION:
        raise PackError(f"{path}: not a feature pack of format {FORMAT} version {VERSION} "
                        f"(format={h5.attrs.get('format')!r}, version={h5.attrs.get('version')!r})")
    made = json.loads(h5.attrs["layout"])
    if made != layout():
        differ = sorted(k for k in set(made) | set(layout()) if made.get(k) != layout().get(k))
        raise PackError(f"{path}: made with another feature layout (differs in {differ}); remove it, then pack its "
                        f"episodes again where their files are (make record-pack) or solve them again (make "
                        f"record-data)")


def pack_names(path: str | os.PathLike) -> list[str]:
    """The episode names a pack holds (kept in memory per file version: a directory is listed often)."""
    stat = Path(path).stat()
    return list(_pack_names(str(Path(path).resolve()), stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=256)
def _pack_names(path: str, mtime_ns: int, size: int) -> tuple[str, ...]:
    with h5py.File(path, "r") as h5:
        _checked(h5, Path(path))
        return tuple(_names(h5))


def _names(h5: h5py.File) -> list[str]:
    return [n.decode() if isinstance(n, bytes) else str(n) for n in h5["names"][()]]


def pack_manifest(path: str | os.PathLike) -> list[dict]:
    """The generator's manifest records kept with a pack (its episodes' and the refusals of their range)."""
    with h5py.File(path, "r") as h5:
        _checked(h5, Path(path))
        text = h5["manifest"][()]
    text = text.decode() if isinstance(text, bytes) else str(text)
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def read_pack(path: str | os.PathLike) -> dict[str, EpisodeFeatures]:
    """{episode name: its features} of a pack, equal to learn.features.extract of the episodes it was made from
    (fresh arrays on every call: the caller may change them)."""
    with h5py.File(path, "r") as h5:
        _checked(h5, Path(path))
        names = _names(h5)
        a = {k: h5[k][()] for k in ("counts", "origin", "meta", "t", "beams", "joint_state", "beam_state",
                                    "joint_bc", "beam_bc", "point_index", "nodes", "node_points")}
    counts = a["counts"]
    if counts.shape != (len(names), 5):
        raise PackError(f"{path}: counts {counts.shape} for {len(names)} episodes")
    F, J, B, P, U = counts.T
    rows = {"t": F, "beams": B, "joint_state": F * J, "beam_state": F * B, "joint_bc": J, "beam_bc": B,
            "point_index": P, "nodes": U, "node_points": F * U}
    starts = {}
    for k, n in rows.items():
        if int(n.sum()) != len(a[k]):
            raise PackError(f"{path}: {k} holds {len(a[k])} rows, its counts {int(n.sum())}")
        starts[k] = np.concatenate([[0], np.cumsum(n)])
    out = []
    for e, name in enumerate(names):
        part = {k: a[k][starts[k][e]:starts[k][e + 1]] for k in rows}
        m = json.loads(a["meta"][e])
        f, j, b = int(F[e]), int(J[e]), int(B[e])
        node_points = part["node_points"].reshape(f, int(U[e]), 3)
        out.append((name, EpisodeFeatures(
            name=name, family=m["family"], design_size=float(m["design_size"]),
            fea_seconds=float(m["fea_seconds"]), fea_load_per_cpu=float(m["fea_load_per_cpu"]),
            t=part["t"], incidence=Incidence.from_beams(part["beams"], j),
            joint_state=part["joint_state"].reshape(f, j, -1), beam_state=part["beam_state"].reshape(f, b, -1),
            joint_bc=part["joint_bc"], beam_bc=part["beam_bc"], origin=a["origin"][e],
            point_nodes=part["nodes"][part["point_index"]], fea_points=node_points[:, part["point_index"]],
            conditions=m["conditions"])))
    return dict(out)


def packed(data_dir: str | os.PathLike) -> dict[str, Path]:
    """{episode name: the pack of `data_dir` holding it} (the last pack in name order wins a name held twice)."""
    return {n: p for p in pack_paths(data_dir) for n in pack_names(p)}
