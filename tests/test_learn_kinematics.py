"""The kinematic update: tree from the fixed joint, exact round trip global <-> parent frames, a zero update is a
rigid motion-free step, and a rigid motion of a parent carries its whole subtree."""
import numpy as np
import pytest
import torch

from data_schema.testing import synthetic_episode
from learn import kinematics
from learn.dataset import GraphSet
from learn.features import extract, rebuild_all_points
from learn.graph import BEAM, JOINT, Incidence
from learn.model import Simulator

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def data():
    return GraphSet.build([extract(synthetic_episode(3, 3, 5, 3, 3, 5, seed=s), name=f"ep{s}.h5") for s in (0, 1)])


def _fixed(data):
    return data.static.joint_bc[:, JOINT.bc.slice("fixed")].numpy()


def test_tree_reaches_every_block_in_breadth_first_order(data):
    t = kinematics.tree(data.static.index, _fixed(data))
    roots = np.flatnonzero(_fixed(data)[:, 0] > 0.5)
    assert len(roots) == 2  # one fixed joint per episode of the union graph
    assert (t.joint_parent.numpy()[roots] == -1).all() and (np.delete(t.joint_parent.numpy(), roots) >= 0).all()
    placed = set(roots.tolist()), set()
    for kind, idx in t.levels:
        for i in idx.tolist():
            if kind == BEAM.name:
                assert int(t.beam_parent[i]) in placed[0]  # a beam is placed after the joint it hangs from
                placed[1].add(i)
            else:
                assert int(t.joint_parent[i]) in placed[1]
                placed[0].add(i)
    assert placed[0] == set(range(data.static.index.n_joints)) and placed[1] == set(range(data.static.index.n_beams))
    # every beam hangs from one of its own joints
    index = data.static.index
    for e in range(len(index.senders)):
        assert int(t.beam_parent[index.edge_beam[e]]) in (int(index.senders[e]), int(index.receivers[e]))


def test_tree_refuses_a_joint_cut_off_from_the_support():
    inc = Incidence.from_beams(np.array([[0, 1], [2, 3]]), 4)
    with pytest.raises(ValueError, match=r"joints \[2, 3\] are not connected to a fixed joint"):
        kinematics.tree(inc.tensors(), np.array([1.0, 0, 0, 0]))


def test_relative_then_place_round_trips_every_frame(data):
    t = kinematics.tree(data.static.index, _fixed(data))
    js, bs = data.joint_state, data.beam_state
    rj, rb = kinematics.relative(js, bs, t)
    jg, bg = kinematics.place(js[..., JOINT.geometry_slice], rj, rb, t)
    assert torch.allclose(jg, js[..., JOINT.geometry_slice], atol=1e-3)
    assert torch.allclose(bg, bs[..., BEAM.geometry_slice], atol=1e-3)


def test_rotating_a_joint_carries_its_subtree_rigidly(data):
    """A block's relative geometry is unchanged when its parent and everything hanging from it move rigidly."""
    t = kinematics.tree(data.static.index, _fixed(data))
    js, bs = data.joint_state[-1], data.beam_state[-1]
    rj, rb = kinematics.relative(js, bs, t)
    c, s = np.cos(0.4), np.sin(0.4)
    R = torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=js.dtype)
    move = lambda g, block: torch.cat([  # noqa: E731
        (R @ g[..., sl].unsqueeze(-1)).squeeze(-1) + (torch.tensor([3.0, -2.0, 7.0]) if f.kind == "point" else 0)
        for f, sl in zip(block.geometry.fields, (block.geometry.slice(f.name) for f in block.geometry.fields))], -1)
    jm = torch.cat([move(js[..., JOINT.geometry_slice], JOINT), js[..., JOINT.stress_slice]], -1)
    bm = torch.cat([move(bs[..., BEAM.geometry_slice], BEAM), bs[..., BEAM.stress_slice]], -1)
    rj2, rb2 = kinematics.relative(jm, bm, t)
    nonroot = t.joint_parent >= 0
    assert torch.allclose(rj2[nonroot], rj[nonroot], atol=1e-3) and torch.allclose(rb2, rb, atol=1e-3)


@pytest.mark.parametrize("frame", ["global", "local"])
def test_kinematic_simulator_keeps_the_fixed_joint_and_trains(data, frame):
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16, 8], "update": "kinematic",
                           "pin_fixed_joint": True, "frame": frame}, data.joint_state, data.beam_state, data.static)
    j, b = model.step(data.joint_state[:3], data.beam_state[:3], data.static, data.t[:3])
    assert j.shape == data.joint_state[:3].shape and b.shape == data.beam_state[:3].shape
    assert torch.isfinite(j).all() and torch.isfinite(b).all()
    root = torch.as_tensor(_fixed(data)[:, 0] > 0.5)
    G = JOINT.geometry_slice
    assert torch.allclose(j[:, root, G], data.joint_state[:3, root, G], atol=1e-3)
    # gradients reach every parameter through the level-by-level placement
    loss = rebuild_all_points(j, b).square().mean()
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())


def test_unknown_update_is_refused_with_the_allowed_values():
    with pytest.raises(ValueError, match="model.update='rigid': must be additive | kinematic"):
        Simulator({"core": "single_gn", "latent": 8, "widths": [8], "update": "rigid",
                   "pca": {t: [1, 1] for t in ("joint_geometry", "joint_stress", "joint_bc", "beam_geometry",
                                               "beam_stress", "beam_bc")}})


def test_compiled_kinematic_rollout_matches_eager_on_designs_with_different_trees():
    from learn.rollout import compile_rollout, graph_inputs, rollout
    fs = [extract(synthetic_episode(3, 3, 5, 3, 3, 5, seed=s), name=f"ep{s}.h5") for s in (2, 3)]
    data = GraphSet.build(fs)
    torch.manual_seed(0)  # an untrained model: keep its rollout (and so the float32 round-off) the same every run
    model = Simulator.fit({"core": "single_gn", "latent": 8, "widths": [16, 8], "update": "kinematic",
                           "pin_fixed_joint": True}, data.joint_state, data.beam_state, data.static).eval()
    trees = [kinematics.tree(GraphSet.build([f]).static.index, f.joint_bc[:, JOINT.bc.slice("fixed")]) for f in fs]
    assert any(not torch.equal(a.beam_parent, b.beam_parent) for a, b in [trees])  # the two designs differ
    compiled = compile_rollout(model, fs[0])
    for f in fs:
        with torch.inference_mode():
            got = compiled(*graph_inputs(f))[2].numpy()
        want = rollout(model, f, steps=f.n_frames - 1).local_points
        assert np.allclose(got, want, atol=1e-3)
    assert len(compiled.traces) == 2
