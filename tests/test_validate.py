"""The validator names the field of every kind of corruption, on disk and through its command line."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from data_schema.checks import EpisodeError
from data_schema.episode import write_episode
from data_schema.testing import synthetic_episode
from data_schema.validate import check, episode_files, validate_episode

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def good(tmp_path) -> Path:
    return write_episode(tmp_path / "good.h5", synthetic_episode())


def _truncate(p: Path) -> None:
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])


def _rewrite(p: Path, name: str, fn) -> None:
    """Replace dataset `name` by fn(its data)."""
    with h5py.File(p, "r+") as h5:
        data = fn(h5[name][()])
        del h5[name]
        h5.create_dataset(name, data=data)


def _set(index, value):
    """fn for _rewrite: a copy with a[index] = value (value may be a function of a)."""
    def fn(a):
        a = a.copy()
        a[index] = value(a) if callable(value) else value
        return a
    return fn


def _delete(p, group, name):
    with h5py.File(p, "r+") as h5:
        if name in h5[group].attrs:
            del h5[group].attrs[name]
        else:
            del h5[group][name]


def _set_attr(p, group, name, value):
    with h5py.File(p, "r+") as h5:
        h5[group].attrs[name] = value


_nan = _set((1, 5, 0), np.nan)
CORRUPTIONS = {  # case: (corrupt(path), field named first, words in its message)
    "truncated": (_truncate, "file", "cannot be opened as HDF5"),
    "not hdf5": (lambda p: p.write_text("not an episode"), "file", "cannot be opened as HDF5"),
    "wrong dtype": (lambda p: _rewrite(p, "frames/stress", lambda a: a.astype(np.float64)), "stress",
                    "dtype float64; expected float32"),
    "wrong int dtype": (lambda p: _rewrite(p, "mesh/node_key", lambda a: a.astype(np.int64)), "node_key",
                        "expected int32"),
    "nan in node_xyz": (lambda p: _rewrite(p, "frames/node_xyz", _nan), "node_xyz", "non-finite"),
    "missing dataset": (lambda p: _delete(p, "mesh", "cell_layer"), "cell_layer", "missing"),
    "missing attribute": (lambda p: _delete(p, "provenance", "seed"), "seed", "missing"),
    "duplicate node key": (lambda p: _rewrite(p, "mesh/node_key", _set(7, lambda a: a[6])), "node_key",
                           "duplicate key"),
    "duplicate cell key": (lambda p: _rewrite(p, "mesh/cell_key", _set(7, lambda a: a[6])), "cell_key",
                           "duplicate key"),
    "unsorted node keys": (lambda p: _rewrite(p, "mesh/node_key", _set([6, 7], lambda a: a[[7, 6]])), "node_key",
                           "lexicographic order"),
    "non-monotone t": (lambda p: _rewrite(p, "frames/t", _set([1, 2], lambda a: a[[2, 1]])), "t",
                       "not strictly increasing"),
    "t beyond 1": (lambda p: _rewrite(p, "frames/t", _set(-1, 1.5)), "t", "expected <= 1"),
    "frame 0 moved": (lambda p: _rewrite(p, "frames/node_xyz", _set((0, 3, 2), 9.0)), "node_xyz", "frame 0"),
    "shape mismatch": (lambda p: _rewrite(p, "mesh/node_xyz0", lambda a: a[:-1]), "node_xyz0", "N ="),
    "uncovered node": (lambda p: _rewrite(p, "mesh/joint_nodes", _set((0, 0, 0, 0), lambda a: a[0, 0, 0, 1])),
                       "joint_nodes", "expected key [0, 0, 0, 0]"),
    "node id out of range": (lambda p: _rewrite(p, "mesh/cell_nodes", _set((0, 0), 10**6)), "cell_nodes",
                             "outside"),
    "inverted cell": (lambda p: _rewrite(p, "mesh/cell_nodes", _set(0, lambda a: a[0, [4, 5, 6, 7, 0, 1, 2, 3]])),
                      "cell_nodes", "inverted"),
    "increments mismatch": (lambda p: _rewrite(p, "provenance/newton_iterations", lambda a: a[:-1]),
                            "newton_iterations", "K ="),
    "mesh attr mismatch": (lambda p: _set_attr(p, "mesh", "nodes_length", 7), "nodes_length", "nl = 5"),
    "wrong version": (lambda p: _set_attr(p, "/", "schema_version", "morphsim.episode/0"), "schema_version",
                      "expected 'morphsim.episode/1'"),
    "bad json": (lambda p: _set_attr(p, "provenance", "solver_stats_json", "{oops"), "solver_stats_json",
                 "not valid JSON"),
}


@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_validator_names_the_field(good, case):
    corrupt, field, words = CORRUPTIONS[case]
    assert validate_episode(good) == []
    corrupt(good)
    problems = validate_episode(good)
    assert problems, f"{case} went unnoticed"
    assert problems[0].startswith(f"{field}: ") and words in problems[0], problems
    with pytest.raises(EpisodeError) as err:
        check(good)
    assert err.value.field == field and err.value.path == good


def test_valid_file_passes_check(good):
    check(good)  # no exception


def test_episode_files_recurses_into_directories(tmp_path):
    (tmp_path / "a" / "b").mkdir(parents=True)
    for name in ("a/x.h5", "a/b/y.h5", "a/b/ignored.h5.1234.tmp", "a/notes.txt"):
        (tmp_path / name).write_text("")
    assert episode_files([tmp_path / "a", tmp_path / "z.h5"]) == [
        tmp_path / "a/b/y.h5", tmp_path / "a/x.h5", tmp_path / "z.h5"]


def test_episode_files_leave_out_files_of_another_declared_format(tmp_path, good):
    """A data directory's features/ holds learn's feature packs (HDF5 with a root `format` attribute, no schema
    version): not episodes, so validating or fingerprinting the directory does not fail on them."""
    import shutil
    d = tmp_path / "data"
    (d / "features").mkdir(parents=True)
    shutil.copy(good, d / "episode_00000.h5")
    with h5py.File(d / "features" / "part.h5", "w") as h5:
        h5.attrs["format"] = "morphsim.features"
    (d / "features" / "broken.h5").write_text("")  # unreadable: kept, for the validator to report
    assert episode_files([d]) == [d / "episode_00000.h5", d / "features" / "broken.h5"]


def _cli(*paths) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "data_schema.validate", *map(str, paths)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


def test_cli_exit_codes(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    good = write_episode(data / "good.h5", synthetic_episode())
    ok = _cli(good)
    assert ok.returncode == 0 and ok.stdout.strip() == f"OK {good}"
    ok_dir = _cli(data)
    assert ok_dir.returncode == 0 and ok_dir.stdout.strip() == f"OK {good}"

    bad = write_episode(data / "bad.h5", synthetic_episode(seed=1))
    _truncate(bad)
    nan = write_episode(data / "nan.h5", synthetic_episode(seed=2))
    _rewrite(nan, "frames/node_xyz", _nan)
    out = _cli(data)
    assert out.returncode == 1
    lines = out.stdout.strip().splitlines()
    assert lines[0].startswith(f"FAIL {bad}: file: cannot be opened as HDF5")
    assert lines[1] == f"OK {good}"
    assert lines[2].startswith(f"FAIL {nan}: node_xyz: ")
    assert "Traceback" not in out.stderr and "3 files, 2 failed" in out.stderr

    missing = _cli(tmp_path / "nope.h5")
    assert missing.returncode == 1 and "FAIL" in missing.stdout and "not found" in missing.stdout
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _cli(empty).returncode == 1
    assert _cli().returncode == 2  # usage error: no path given
