"""XDMF views (data_schema.view): what ParaView reads back equals the episode; von Mises against closed forms."""
from __future__ import annotations

import subprocess
import sys

import meshio
import numpy as np
import pytest

from data_schema.episode import write_episode
from data_schema.testing import synthetic_episode
from data_schema.view import von_mises, write_episode_view, write_series


def read_view(path):
    reader = meshio.xdmf.TimeSeriesReader(path)
    points, cells = reader.read_points_cells()
    steps = [reader.read_data(k) for k in range(reader.num_steps)]
    return points, cells, steps


def test_von_mises_closed_forms():
    s, tau, p = 3.0, 2.0, 5.0
    assert von_mises(np.array([s, 0, 0, 0, 0, 0])) == pytest.approx(s)  # uniaxial: sigma_vM = |sigma|
    assert von_mises(np.array([0, 0, 0, tau, 0, 0])) == pytest.approx(np.sqrt(3) * tau)  # pure shear
    assert von_mises(np.array([p, p, p, 0, 0, 0])) == pytest.approx(0.0)  # hydrostatic: no distortion
    assert von_mises(np.array([[s, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, tau]])) == pytest.approx([s, np.sqrt(3) * tau])


def test_episode_view_reads_back_as_the_episode(tmp_path):
    ep = synthetic_episode(frames=4)
    path = write_episode(tmp_path / "episode_00000.h5", ep)
    view = write_episode_view(path)
    assert view.name == "episode_00000.view.xdmf" and (tmp_path / "episode_00000.view.h5").exists()
    points, cells, steps = read_view(view)
    np.testing.assert_allclose(points, ep.node_xyz0, atol=1e-5)
    assert cells[0].type == "hexahedron" and (cells[0].data == ep.cell_nodes).all()
    assert [t for t, _, _ in steps] == pytest.approx(ep.t)
    w = ep.quad_weights / ep.quad_weights.sum()
    for k, (_, point_data, cell_data) in enumerate(steps):
        np.testing.assert_allclose(point_data["displacement"], ep.node_xyz[k] - ep.node_xyz0, atol=1e-5)
        mean = np.einsum("cqs,q->cs", ep.stress[k].astype(float), w)
        np.testing.assert_allclose(cell_data["stress"][0], mean, atol=1e-6)
        np.testing.assert_allclose(cell_data["von_mises"][0], von_mises(mean), atol=1e-6)
        assert (cell_data["block"][0] == ep.cell_key[:, 0]).all()


def test_view_never_overwrites_an_episode_and_checks_shapes(tmp_path):
    ep = synthetic_episode()
    path = write_episode(tmp_path / "a.h5", ep)
    before = path.read_bytes()
    with pytest.raises(ValueError, match="is an episode"):
        write_episode_view(path, tmp_path / "a.xdmf")  # meshio would put its data in a.h5
    assert path.read_bytes() == before
    with pytest.raises(ValueError, match=r"point_data\['u'\]"):
        write_series(tmp_path / "b.xdmf", ep.node_xyz0, ep.cell_nodes, np.array([0.0, 1.0]),
                     point_data={"u": np.zeros((2, 3, 3))})
    assert not list(tmp_path.glob("b.*")) and not list(tmp_path.glob(".view_*"))


def test_cli_writes_a_view_per_episode_of_a_directory(tmp_path):
    for i in range(2):
        write_episode(tmp_path / "data" / f"episode_{i:05d}.h5", synthetic_episode(seed=i))
    out = subprocess.run([sys.executable, "-m", "data_schema.view", str(tmp_path / "data"), "--out",
                          str(tmp_path / "views")], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert sorted(p.name for p in (tmp_path / "views").iterdir()) == [
        "episode_00000.view.h5", "episode_00000.view.xdmf", "episode_00001.view.h5", "episode_00001.view.xdmf"]
    assert not list(tmp_path.glob("*.h5"))  # nothing left in the working directory
    bad = subprocess.run([sys.executable, "-m", "data_schema.view", str(tmp_path / "data" / "episode_00000.h5"),
                          "--out", str(tmp_path / "data" / "episode_00001.xdmf")], capture_output=True, text=True)
    assert bad.returncode == 2 and "is an episode" in bad.stderr
