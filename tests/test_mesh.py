"""Keyed hexahedral meshes: keys unique and complete, counts from the presets, conformity, quality, CLI."""
from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from fea_factory.design import lattice_design
from fea_factory.mesh import MeshPreset, build_keyed_mesh, scaled_jacobian
from fea_factory.sample import sample_designs

ROOT = Path(__file__).resolve().parent.parent
PRESETS = {p.stem: MeshPreset.from_mapping(OmegaConf.load(p)) for p in (ROOT / "conf/mesh").glob("*.yaml")}
HEX_FACES = [[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
MIN_SCALED_JACOBIAN = 0.5  # joint corner angles >= 45 deg give >= sin 45 = 0.71 in the plane; margin for jitter


def grid_cfg():
    return OmegaConf.load(ROOT / "conf/grid/default.yaml"), OmegaConf.load(ROOT / "conf/blocks/default.yaml")


@pytest.fixture(scope="module")
def designs():
    g, b = grid_cfg()
    return sample_designs(g, b, n=100, seed=123)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_keys_unique_complete_and_counts_match_the_preset(designs, name):
    p = PRESETS[name]
    for d in designs[:10]:
        m = build_keyed_mesh(d, p)
        assert (m.n_nodes, m.n_cells) == p.counts(d.n_joints, d.n_beams)
        assert len(np.unique(m.node_key, axis=0)) == m.n_nodes
        assert len(np.unique(m.cell_key, axis=0)) == m.n_cells
        # ids are in key order
        assert (np.lexsort(m.node_key.T[::-1]) == np.arange(m.n_nodes)).all()
        assert (np.lexsort(m.cell_key.T[::-1]) == np.arange(m.n_cells)).all()
        # block tables cover every id; each node's own key points back at it
        assert set(np.concatenate([m.joint_nodes.ravel(), m.beam_nodes.ravel()])) == set(range(m.n_nodes))
        assert set(np.concatenate([m.joint_cells.ravel(), m.beam_cells.ravel()])) == set(range(m.n_cells))
        J = d.n_joints
        for nid in (0, m.n_nodes // 2, m.n_nodes - 1):
            b, i, j, k = m.node_key[nid]
            table = m.joint_nodes[b] if b < J else m.beam_nodes[b - J]
            assert table[i, j, k] == nid
        # odd counts: mid-length, mid-width and mid-thickness node planes exist
        nl, nw, nh = p.nodes_length, p.nodes_width, p.nodes_height
        assert nl % 2 == nw % 2 == nh % 2 == 1
        np.testing.assert_allclose(m.node_xyz[m.beam_nodes[:, :, :, nh // 2], 2], d.thickness / 2)


def test_conforming_no_duplicate_nodes_each_interior_face_twice(designs):
    for d in designs[:10]:
        m = build_keyed_mesh(d, PRESETS["default"])
        faces = Counter(tuple(sorted(c[f])) for c in m.cell_nodes for f in HEX_FACES)
        assert set(faces.values()) <= {1, 2}
        assert len(np.unique(np.round(m.node_xyz, 9), axis=0)) == m.n_nodes
        # beam end faces are exactly the joint side faces they meet
        for b, (a, c) in enumerate(d.beams.tolist()):
            assert set(m.beam_nodes[b, 0].ravel()) <= set(m.joint_nodes[a].ravel())
            assert set(m.beam_nodes[b, -1].ravel()) <= set(m.joint_nodes[c].ravel())


def test_scaled_jacobian_of_100_sampled_designs(designs):
    meshes = [build_keyed_mesh(d, PRESETS["default"]) for d in designs]
    worst = min(scaled_jacobian(m.node_xyz, m.cell_nodes).min() for m in meshes)
    assert worst > MIN_SCALED_JACOBIAN, f"min scaled Jacobian {worst:.3f}"


def test_layers_and_print_angles_follow_the_actuator_kind():
    xs, ys = np.meshgrid([0.0, 60.0], [0.0, 60.0], indexing="ij")
    d = lattice_design(np.stack([xs, ys], -1), ["down", "up", "passive", "down"], (0, 0))
    m = build_keyed_mesh(d, PRESETS["coarse"])
    J = d.n_joints
    for b, kind in enumerate(d.kinds):
        cells = m.beam_cells[b].ravel()
        axis = d.joint_xy[d.beams[b, 1]] - d.joint_xy[d.beams[b, 0]]
        along = np.degrees(np.arctan2(axis[1], axis[0])) % 180
        across = (along + 90) % 180
        bottom = m.cell_print_angle[cells[m.cell_layer[cells] == 0]]
        top = m.cell_print_angle[cells[m.cell_layer[cells] == 1]]
        want = {"down": (along, across), "up": (across, along), "passive": (across, across)}[kind]
        np.testing.assert_allclose(bottom, want[0])
        np.testing.assert_allclose(top, want[1])
    joint_cells = m.joint_cells[0]  # alternating layers through the joint
    a0, a1 = m.cell_print_angle[joint_cells[:, :, 0]], m.cell_print_angle[joint_cells[:, :, 1]]
    assert np.allclose(np.abs(a0 - a1) % 180, 90)
    assert (m.cell_key[:, 0] < J).sum() == m.joint_cells.size


def test_mesh_is_deterministic(designs):
    a, b = build_keyed_mesh(designs[0], PRESETS["default"]), build_keyed_mesh(designs[0], PRESETS["default"])
    assert np.array_equal(a.node_xyz, b.node_xyz) and np.array_equal(a.cell_nodes, b.cell_nodes)


def test_even_node_count_is_refused():
    from fea_factory.design import DesignError

    with pytest.raises(DesignError, match="nodes_width"):
        MeshPreset(9, 4, 3)


def test_mesh_cli_writes_xdmf_and_key_tables(tmp_path, designs):
    pytest.importorskip("gmsh")
    import h5py
    import meshio

    designs[3].save(tmp_path / "d.json")
    r = subprocess.run([sys.executable, "-m", "fea_factory.mesh", f"design={tmp_path / 'd.json'}",
                        f"out={tmp_path / 'm'}", "mesh=coarse"], cwd=ROOT, capture_output=True, text=True,
                       stdin=subprocess.DEVNULL, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    info = json.loads(r.stdout.strip().splitlines()[-1])
    assert info["cells"] == PRESETS["coarse"].counts(designs[3].n_joints, designs[3].n_beams)[1]
    vm = meshio.read(tmp_path / "m/mesh.xdmf")
    assert vm.cells[0].type == "hexahedron" and len(vm.cells[0].data) == info["cells"]
    assert {"block", "layer", "print_angle"} <= set(vm.cell_data)
    with h5py.File(tmp_path / "m/keys.h5") as f:
        assert f["node_key"].shape == (info["nodes"], 4)
    assert (tmp_path / "m/mesh.msh").stat().st_size > 0
    assert not (tmp_path / "m/.tmp_mesh").exists()
