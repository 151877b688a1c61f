"""Validate episode files against the schema: python -m data_schema.validate PATH... (files or directories).

Prints "OK path" or "FAIL path: field: message" (the first problem) per file; exits 1 if any file failed.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Iterable

import h5py
import numpy as np

from data_schema.checks import EpisodeError, Problem, episode_problems
from data_schema.episode import EPISODE_SUFFIX, missing_fields, read_open, schema_version
from data_schema.fields import FIELDS, SCHEMA_VERSION, SCHEMA_VERSION_ATTR

__all__ = ["EpisodeError", "validate_episode", "check", "episode_files", "main"]


def _stored_type_problems(h5: h5py.File) -> list[Problem]:
    """Datasets must be stored with exactly their declared dtype, attributes with their declared kind."""
    out = []
    for f in FIELDS:
        group = h5[f.group]
        if f.is_attr:
            value = group.attrs[f.name]
            kind = {"str": (str, bytes), "int64": (int, np.integer), "float64": (float, np.floating)}[f.dtype]
            if not isinstance(value, kind) or isinstance(value, (bool, np.bool_)):
                out.append((f.name, f"attribute of type {type(value).__name__}; expected {f.dtype}"))
        elif group[f.name].dtype != np.dtype(f.dtype):
            out.append((f.name, f"dtype {group[f.name].dtype}; expected {f.dtype}"))
    return out


def _problems(path: Path) -> list[Problem]:
    try:
        h5 = h5py.File(path, "r")
    except OSError as e:
        why = "not found" if not path.exists() else f"cannot be opened as HDF5 (truncated or not an episode): {e}"
        return [("file", why)]
    try:
        with h5:
            version = schema_version(h5)
            if version != SCHEMA_VERSION:
                return [(SCHEMA_VERSION_ATTR, f"is {version!r}; expected {SCHEMA_VERSION!r}")]
            missing = missing_fields(h5)
            if missing:
                return [(f.name, f"missing (expected at {f.path})") for f in missing]
            problems = _stored_type_problems(h5)
            if problems:
                return problems
            ep = read_open(h5, path=path)
    except OSError as e:  # a damaged chunk or header read after opening
        return [("file", f"read failed (truncated or corrupt): {e}")]
    return episode_problems(ep)


def validate_episode(path: str | os.PathLike) -> list[str]:
    """Every problem of an episode file as "field: message"; an empty list means the file is valid."""
    return [f"{field}: {message}" for field, message in _problems(Path(path))]


def check(path: str | os.PathLike) -> None:
    """Raise EpisodeError(path, field, message) for the first problem of an episode file."""
    problems = _problems(Path(path))
    if problems:
        raise EpisodeError(path, *problems[0])


def episode_files(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Files given, plus every *.h5 file under the directories given (recursively, sorted) that does not declare
    itself another format (a root `format` attribute and no schema version: learn's feature packs, kept in a data
    directory's features/)."""
    out: list[Path] = []
    for p in map(Path, paths):
        out += [f for f in sorted(p.rglob("*" + EPISODE_SUFFIX)) if not _another_format(f)] if p.is_dir() else [p]
    return out


def _another_format(path: Path) -> bool:
    try:
        with h5py.File(path, "r") as h5:
            return "format" in h5.attrs and SCHEMA_VERSION_ATTR not in h5.attrs
    except OSError:
        return False  # not readable as HDF5: an episode file gone wrong, for the validator to report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m data_schema.validate", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", help="episode files or directories holding them")
    parser.add_argument("-q", "--quiet", action="store_true", help="print failures only")
    args = parser.parse_args(argv)
    files = episode_files(args.paths)
    failed = 0
    for p in args.paths:
        if Path(p).is_dir() and not any(f.is_relative_to(p) for f in files):
            print(f"FAIL {p}: file: directory holds no *{EPISODE_SUFFIX} files")
            failed += 1
    for path in files:
        problems = _problems(path)
        if problems:
            failed += 1
            print(f"FAIL {path}: {problems[0][0]}: {problems[0][1]}", flush=True)
        elif not args.quiet:
            print(f"OK {path}", flush=True)
    print(f"{len(files)} files, {failed} failed", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
