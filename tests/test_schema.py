"""Episode format: the declaration, the synthetic episode, round trips and the atomic writer."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

import data_schema.episode as episode_mod
from data_schema.checks import EpisodeError, corner_nodes
from data_schema.episode import EPISODE_SUFFIX, Episode, read_episode, write_episode
from data_schema.fields import FIELDS, GROUPS, SCHEMA_VERSION, markdown_table
from data_schema.testing import assert_episodes_equal, synthetic_episode
from data_schema.validate import validate_episode

REPO = Path(__file__).resolve().parents[1]


def run_python(code: str, *args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], cwd=REPO, capture_output=True,
                          text=True, timeout=120, **kw)


@pytest.fixture(scope="module")
def ep() -> Episode:
    return synthetic_episode()


# ---------------------------------------------------------------------------------------------- declaration
def test_episode_attributes_are_the_fields(ep):
    assert [f.name for f in FIELDS] == [f.name for f in Episode.__dataclass_fields__.values()]
    assert set(GROUPS) == {"design", "mesh", "frames", "provenance"}
    assert {f.name for f in FIELDS if f.per_frame} == {"t", "node_xyz", "stress"}


def test_readme_table_is_generated_from_fields():
    readme = (REPO / "data_schema" / "README.md").read_text()
    assert markdown_table() in readme, "run `python -m data_schema.fields --markdown` and paste it into the README"
    out = run_python("from data_schema.fields import main; main(['--markdown'])")
    assert out.returncode == 0 and out.stdout.strip() == markdown_table()


# ---------------------------------------------------------------------------------------------- synthetic episode
def test_synthetic_episode_is_consistent(ep):
    assert (ep.n_joints, ep.n_beams, ep.n_frames) == (4, 4, 3)
    assert ep.n_nodes == 4 * 3 * 3 * 3 + 4 * 3 * 3 * 3 and ep.n_cells == 4 * 2 * 2 * 2 + 4 * 4 * 2 * 2
    # keys sorted, tables match keys, beam end faces are the joints' side nodes (shared, same coordinates)
    assert (np.diff(ep.node_key[:, 0]) >= 0).all()
    for b, (a, c) in enumerate(ep.beams):
        assert set(ep.node_key[ep.beam_nodes[b, 0].ravel(), 0]) == {a}
        assert set(ep.node_key[ep.beam_nodes[b, -1].ravel(), 0]) == {c}
    # joint top face at z = thickness, bottom at 0; beam interior i=1 one cell length from the joint side
    assert np.allclose(ep.node_xyz0[ep.joint_nodes[..., -1], 2], ep.thickness)
    assert np.allclose(ep.node_xyz0[ep.joint_nodes[..., 0], 2], 0.0)
    # hex8 cells are right-handed: (x1 - x0) x (x3 - x0) . (x4 - x0) > 0
    x = ep.node_xyz0[ep.cell_nodes]
    assert (np.einsum("ci,ci->c", np.cross(x[:, 1] - x[:, 0], x[:, 3] - x[:, 0]), x[:, 4] - x[:, 0]) > 0).all()
    assert np.array_equal(np.sort(ep.cell_nodes[ep.beam_cells.ravel()], axis=1),
                          np.sort(corner_nodes(ep.beam_nodes).reshape(-1, 8), axis=1))
    # the fixed joint stays put, the rest morphs smoothly; the stress relaxes from the prestress
    fixed = ep.joint_nodes[ep.fixed_joint].ravel()
    assert np.allclose(ep.node_xyz[:, fixed], ep.node_xyz0[fixed], atol=1e-4)
    assert np.abs(ep.node_xyz[-1] - ep.node_xyz0).max() > 5.0
    assert np.isfinite(ep.stress).all() and np.abs(ep.stress[0]).max() > 0
    assert ep.design_size > 30 and ep.solver_stats["increments"] == len(ep.increment_t)


def test_synthetic_episode_is_deterministic_and_sized():
    a, b = synthetic_episode(seed=3), synthetic_episode(seed=3)
    assert_episodes_equal(a, b)
    big = synthetic_episode(nx=3, ny=2, nl=7, nw=5, nh=3, frames=5, seed=1)
    assert (big.n_joints, big.n_beams, big.n_frames) == (6, 7, 5)
    assert big.beam_nodes.shape == (7, 7, 5, 3) and big.joint_cells.shape == (6, 4, 4, 2)


# ---------------------------------------------------------------------------------------------- round trip
def test_round_trip(ep, tmp_path):
    path = tmp_path / f"ep{EPISODE_SUFFIX}"
    assert write_episode(path, ep) == path
    back = read_episode(path)
    assert_episodes_equal(ep, back)
    assert validate_episode(path) == []
    assert list(tmp_path.iterdir()) == [path], "no temporary file is left behind"


def test_layout_on_disk(ep, tmp_path):
    path = write_episode(tmp_path / "ep.h5", ep)
    with h5py.File(path, "r") as h5:
        assert h5.attrs["schema_version"] == SCHEMA_VERSION
        assert h5["frames/node_xyz"].chunks == (1, ep.n_nodes, 3)
        assert h5["frames/stress"].compression == "gzip" and h5["frames/stress"].shuffle
        assert h5["frames/stress"].compression_opts == 4
        assert h5["mesh"].attrs["nodes_length"] == 5 and h5["design"].attrs["family"] == "synthetic"
        assert h5["provenance/newton_iterations"].dtype == np.int32


@pytest.mark.parametrize("frames, expect", [(None, [0, 1, 2]), (-1, [2]), (slice(1, None), [1, 2]),
                                            ([2, 0], [2, 0]), ([1, 1], [1, 1]), (np.array([0, 2]), [0, 2])])
def test_read_some_frames(ep, tmp_path, frames, expect):
    path = write_episode(tmp_path / "ep.h5", ep)
    part = read_episode(path, frames=frames)
    assert np.array_equal(part.t, ep.t[expect])
    assert np.array_equal(part.node_xyz, ep.node_xyz[expect])
    assert np.array_equal(part.stress, ep.stress[expect])
    assert np.array_equal(part.node_key, ep.node_key)


def test_writer_casts_to_declared_dtypes(ep, tmp_path):
    loose = ep.replace(node_key=ep.node_key.astype(np.int64), node_xyz=ep.node_xyz.astype(np.float64),
                       cell_layer=ep.cell_layer.astype(np.int64), seed=np.int64(ep.seed), beam_width=7)
    back = read_episode(write_episode(tmp_path / "ep.h5", loose))
    assert back.node_key.dtype == np.int32 and back.node_xyz.dtype == np.float32 and back.cell_layer.dtype == np.int8
    assert type(back.seed) is int and back.beam_width == 7.0 and type(back.beam_width) is float


@pytest.mark.parametrize("field, value, words", [
    ("node_key", lambda e: e.node_key.astype(np.float64), "cannot be stored as int32"),
    ("node_xyz", lambda e: e.node_xyz[:, :5], "node_xyz"),
    ("stress", lambda e: e.stress[..., :5], "expected 6"),
    ("joint_nodes", lambda e: e.joint_nodes[..., 0], "axes"),
    ("cell_layer", lambda e: e.cell_layer.astype(np.int64) + 1000, "do not fit in int8"),
    ("seed", lambda e: "7", "expected int"),
    ("family", lambda e: 3, "expected str"),
    ("t", lambda e: e.t[[0, 2, 1]], "not strictly increasing"),
    ("node_xyz", lambda e: np.where(np.arange(e.n_nodes)[None, :, None] == 3, np.nan, e.node_xyz), "non-finite"),
])
def test_writer_rejects_bad_fields(ep, tmp_path, field, value, words):
    path = tmp_path / "ep.h5"
    with pytest.raises(ValueError) as err:
        write_episode(path, ep.replace(**{field: value(ep)}))
    assert isinstance(err.value, EpisodeError) and err.value.field == field
    assert words in str(err.value) and field in str(err.value)
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------- atomic writes
def test_failed_write_leaves_old_file_and_no_temporary(ep, tmp_path, monkeypatch):
    path = write_episode(tmp_path / "ep.h5", ep)
    old = path.read_bytes()
    calls = []
    real = episode_mod._create

    def failing(group, f, value):
        calls.append(f.name)
        if f.name == "node_xyz":
            raise RuntimeError("disk full (simulated)")
        real(group, f, value)

    monkeypatch.setattr(episode_mod, "_create", failing)
    with pytest.raises(RuntimeError, match="simulated"):
        write_episode(path, synthetic_episode(seed=1))
    assert "node_key" in calls, "the failure happened midway through the file"
    assert path.read_bytes() == old
    assert list(tmp_path.iterdir()) == [path]
    with pytest.raises(RuntimeError):
        write_episode(tmp_path / "new.h5", ep)
    assert not (tmp_path / "new.h5").exists()


def test_killed_writer_leaves_no_file_at_final_path(tmp_path):
    """SIGKILL in the middle of a write: the final path never appears (only a *.tmp remains)."""
    target = tmp_path / "ep.h5"
    proc = subprocess.Popen([sys.executable, "-c", textwrap.dedent("""
        import sys, time
        import data_schema.episode as m
        from data_schema.testing import synthetic_episode
        real = m._create
        def slow(group, f, value):
            real(group, f, value)
            if f.name == "node_xyz":
                group.file.flush()
                print("midway", flush=True)
                time.sleep(60)
        m._create = slow
        m.write_episode(sys.argv[1], synthetic_episode())
        """), str(target)], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "midway"
        leftovers = list(tmp_path.iterdir())
        assert len(leftovers) == 1 and leftovers[0].name.endswith(".tmp") and not target.exists()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
    assert not target.exists()
    assert validate_episode(leftovers[0]), "the leftover temporary file is an incomplete episode"


# ---------------------------------------------------------------------------------------------- isolation
def test_import_without_solver_or_torch(tmp_path):
    out = run_python("""
        import sys
        for name in ("dolfinx", "gmsh", "torch", "mpi4py", "petsc4py", "fea_factory"):
            sys.modules[name] = None  # any import of these raises ImportError
        import data_schema, data_schema.fields, data_schema.checks, data_schema.episode
        import data_schema.validate, data_schema.testing
        from data_schema.episode import write_episode
        from data_schema.testing import synthetic_episode
        from data_schema.validate import validate_episode
        p = write_episode(sys.argv[1], synthetic_episode())
        assert validate_episode(p) == []
        print("ok")
        """, str(tmp_path / "ep.h5"))
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_written_file_has_umask_permissions_and_parents_are_created(ep, tmp_path):
    old = os.umask(0o022)
    try:
        path = write_episode(tmp_path / "a" / "b" / "ep.h5", ep)
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o644
