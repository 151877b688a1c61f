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


class InUse(RuntimeError):
    """Another live process holds the lock."""


@contextlib.contextmanager
def held(lock: str | os.PathLike, what: str, error: type[InUse] = InUse) -> Iterator[Path]:
    """Hold `lock`, a file holding the owner's pid, for the block: a second process that asks while the owner lives
    gets `error` naming `what` and the owner, instead of working on the same files (a training's checkpoints, a
    generator's episodes and the temporaries it cleans up); a lock whose process is gone is taken over."""
    lock = Path(lock)
    lock.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            break
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or 0)
                os.kill(pid, 0)
            except (ValueError, ProcessLookupError, FileNotFoundError):
                lock.unlink(missing_ok=True)  # stale: its process has ended
                continue
            except PermissionError:
                pass
            raise error(f"{what} is in use by process {pid} (remove {lock} if that is wrong)")
    else:
        raise error(f"{what}: could not take {lock}")
    try:
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        yield lock
    finally:
        lock.unlink(missing_ok=True)
