"""Episode: one FEA run in memory (attributes named like the fields), and its atomic HDF5 writer and reader."""
from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, Sequence

import h5py
import numpy as np

from data_schema.atomic import replacing
from data_schema.checks import EpisodeError, coerce, episode_problems
from data_schema.fields import FIELDS, SCHEMA_VERSION, SCHEMA_VERSION_ATTR, Field

EPISODE_SUFFIX = ".h5"
COMPRESSION = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
COMPRESS_MIN_BYTES = 4096  # smaller datasets are stored contiguous and uncompressed

Frames = int | slice | Sequence[int] | np.ndarray | None


def design_size(joint_xy: np.ndarray) -> float:
    """Larger side (mm) of the bounding box of the joint centres [J, 2]: the scale of every relative error
    (fea_factory.design.Design.size is this too)."""
    joint_xy = np.asarray(joint_xy)
    return float((joint_xy.max(axis=0) - joint_xy.min(axis=0)).max())


class _EpisodeMethods:
    """Derived quantities of an Episode (the attributes themselves come from data_schema.fields.FIELDS)."""

    @property
    def n_frames(self) -> int:
        return len(self.t)

    @property
    def n_nodes(self) -> int:
        return len(self.node_key)

    @property
    def n_cells(self) -> int:
        return len(self.cell_key)

    @property
    def n_joints(self) -> int:
        return len(self.joint_xy)

    @property
    def n_beams(self) -> int:
        return len(self.beams)

    @property
    def design_size(self) -> float:
        """Larger side (mm) of the bounding box of the joint centres: the scale of relative errors."""
        return design_size(self.joint_xy)

    @property
    def solver_stats(self) -> dict:
        return json.loads(self.solver_stats_json)

    def replace(self, **changes: Any) -> "Episode":
        """A shallow copy with some fields replaced."""
        return dataclasses.replace(self, **changes)

    def __repr__(self) -> str:
        return (f"Episode(J={self.n_joints}, B={self.n_beams}, N={self.n_nodes}, C={self.n_cells}, "
                f"F={self.n_frames}, family={self.family!r}, seed={self.seed})")


Episode = dataclasses.make_dataclass(
    "Episode", [(f.name, f.pytype) for f in FIELDS], bases=(_EpisodeMethods,), repr=False, eq=False,
    namespace={"__module__": __name__,
               "__doc__": "One episode; one attribute per field of data_schema.fields.FIELDS, named alike."},
)


# --------------------------------------------------------------------------------------------------- write
def _cast(ep: Episode, path: Any) -> Episode:
    """ep with every field cast to its declared type; EpisodeError (a ValueError) naming the first bad field."""
    values = {}
    for f in FIELDS:
        values[f.name], why = coerce(f, getattr(ep, f.name))
        if why is not None:
            raise EpisodeError(path, f.name, why)
    return Episode(**values)


def _create(group: h5py.Group, f: Field, value: Any) -> None:
    if f.is_attr:
        group.attrs[f.name] = value if f.dtype == "str" else np.dtype(f.dtype).type(value)
        return
    opts: dict[str, Any] = {}
    if value.nbytes >= COMPRESS_MIN_BYTES:
        opts.update(COMPRESSION)
        if f.per_frame and value.ndim > 1:
            opts["chunks"] = (1, *value.shape[1:])
    group.create_dataset(f.name, data=value, **opts)


def write_episode(path: str | os.PathLike, ep: Episode) -> Path:
    """Check `ep` (EpisodeError, a ValueError naming the field, on any problem), then write it atomically.

    The file is written to a temporary file beside `path`, flushed to disk and renamed over `path`:
    `path` either keeps its old content or holds the complete new episode, never a partial one.
    """
    path = Path(path)
    ep = _cast(ep, path)
    problems = episode_problems(ep)
    if problems:
        raise EpisodeError(path, *problems[0])
    with replacing(path) as tmp:
        with h5py.File(tmp, "w") as h5:
            h5.attrs[SCHEMA_VERSION_ATTR] = SCHEMA_VERSION
            for f in FIELDS:
                _create(h5.require_group(f.group), f, getattr(ep, f.name))
    return path


# --------------------------------------------------------------------------------------------------- read
def frame_indices(n_frames: int, frames: Frames) -> np.ndarray:
    """Frame numbers selected by `frames` (None: all; int, slice or sequence; negative counts from the end)."""
    if frames is None:
        return np.arange(n_frames)
    idx = np.atleast_1d(np.arange(n_frames)[frames if not isinstance(frames, (list, tuple)) else list(frames)])
    return idx.astype(np.int64)


def _read_frames(dset: h5py.Dataset, idx: np.ndarray) -> np.ndarray:
    if len(idx) and (np.diff(idx) == 1).all():
        return dset[idx[0]: idx[-1] + 1]
    uniq, inverse = np.unique(idx, return_inverse=True)  # h5py needs increasing indices
    return dset[uniq][inverse] if len(uniq) else dset[:0]


def read_attr(group: h5py.Group, f: Field) -> Any:
    value = group.attrs[f.name]
    if f.dtype == "str":
        return value.decode("utf-8") if isinstance(value, bytes) else str(value)
    return f.pytype(value)


def missing_fields(h5: h5py.File) -> list[Field]:
    """Declared fields absent from an open file."""
    out = []
    for f in FIELDS:
        group = h5.get(f.group)
        if not isinstance(group, h5py.Group):
            out.append(f)
        elif f.is_attr and f.name not in group.attrs:
            out.append(f)
        elif not f.is_attr and not isinstance(group.get(f.name), h5py.Dataset):
            out.append(f)
    return out


def schema_version(h5: h5py.File) -> str | None:
    version = h5.attrs.get(SCHEMA_VERSION_ATTR)
    return version.decode() if isinstance(version, bytes) else version


def read_open(h5: h5py.File, frames: Frames = None, path: Any = None) -> Episode:
    """Episode from an open file; only the selected frames of the per-frame fields are read."""
    path = path if path is not None else h5.filename
    version = schema_version(h5)
    if version != SCHEMA_VERSION:
        raise EpisodeError(path, SCHEMA_VERSION_ATTR, f"is {version!r}; expected {SCHEMA_VERSION!r}")
    missing = missing_fields(h5)
    if missing:
        raise EpisodeError(path, missing[0].name, f"missing (expected at {missing[0].path})")
    idx = frame_indices(h5["frames/t"].shape[0], frames)
    values = {}
    for f in FIELDS:
        group = h5[f.group]
        if f.is_attr:
            values[f.name] = read_attr(group, f)
        elif f.per_frame:
            values[f.name] = _read_frames(group[f.name], idx)
        else:
            values[f.name] = group[f.name][()]
    return Episode(**values)


def read_episode(path: str | os.PathLike, frames: Frames = None) -> Episode:
    """Read an episode file; `frames` selects frames (int, slice or sequence of ints) to save memory.

    The frame axis is kept even for a single int. Raises OSError for a file HDF5 cannot open and EpisodeError
    for a wrong schema version or a missing field; run data_schema.validate for the full checks.
    """
    with h5py.File(path, "r") as h5:
        return read_open(h5, frames, path)
