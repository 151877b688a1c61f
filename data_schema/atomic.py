"""Atomic file writes: a file either keeps its old content or holds the complete new one, never a partial one.

Everything the project writes for other tools to read (episodes, checkpoints, designs, JSON reports, tables) goes
through `replacing`: the content is written to a unique temporary file beside the target, flushed to disk and
renamed over it; a failed or killed writer leaves at most a `<name>.<hex>.tmp` beside it, never a half target.
"""
from __future__ import annotations

import contextlib
import csv
import os
import secrets
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

TMP_SUFFIX = ".tmp"  # "<name>.<random>.tmp": an unfinished write; safe to delete when no writer runs


def fsync(path: str | os.PathLike) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """Yields a fresh temporary path beside `path` (created empty, unique); when the block ends without an
    exception the temporary file is synced and renamed over `path`, otherwise it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{secrets.token_hex(4)}{TMP_SUFFIX}")
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))  # unique; mode as the umask allows
    try:
        yield tmp
        fsync(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    try:
        fsync(path.parent)  # makes the rename durable
    except OSError:
        pass  # best effort: not every platform can open or fsync a directory


def write_text(path: str | os.PathLike, text: str) -> Path:
    """`path` atomically replaced by `text` (UTF-8)."""
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_csv(path: str | os.PathLike, rows: Iterable[Mapping], fieldnames: list[str],
              comments: Iterable[str] = ()) -> Path:
    """`path` atomically replaced by a CSV: '# ' comment lines first (provenance), a header of `fieldnames`, then
    one line per row (keys outside `fieldnames` ignored)."""
    with replacing(path) as tmp, open(tmp, "w", newline="") as f:
        for c in comments:
            f.write(f"# {c}\n")
        w = csv.DictWriter(f, fieldnames=fieldnames, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return Path(path)
