"""learn.graph / features / symmetry: incidence, named feature layout, rotation and translation consistency."""
import numpy as np
import pytest

from data_schema.testing import synthetic_episode
from learn.features import BEAM_POINTS, JOINT_POINTS, extract, rebuild_all_points, shared_point_pairs, welded
from learn.graph import BEAM, JOINT, Incidence, disjoint_union
from learn.symmetry import rotate_stress, rotation_z, voigt_to_tensor


@pytest.fixture(scope="module")
def episode():
    return synthetic_episode(nx=3, ny=2, nl=5, nw=3, nh=3, frames=4, seed=3)


def test_incidence_two_directed_edges_per_beam(episode):
    inc = Incidence.from_beams(episode.beams, len(episode.joint_xy))
    J, B = len(episode.joint_xy), len(episode.beams)
    assert (inc.n_joints, inc.n_beams, inc.n_edges) == (J, B, 2 * B)
    for b, (a, c) in enumerate(episode.beams):
        edges = np.where(inc.edge_beam == b)[0]
        assert sorted(zip(inc.senders[edges], inc.receivers[edges])) == sorted([(a, c), (c, a)])
    adj = inc.adjacency()
    assert adj.shape == (B, J) and (adj.sum(axis=1) == 2).all()
    union, jo, bo = disjoint_union([inc, inc])
    assert union.n_edges == 4 * B and jo.tolist() == [0, J, 2 * J] and union.senders[2 * B:].min() >= J


def test_layout_is_named_and_sized_once():
    assert JOINT.geometry.size == 18 and JOINT.stress.size == 48 and JOINT.bc.size == 4
    assert BEAM.geometry.size == 27 and BEAM.stress.size == 72 and BEAM.bc.size == 6
    assert JOINT.geometry.slice("extrusion") == slice(15, 18)
    assert BEAM.origin_slice == BEAM.geometry.slice("middle_center")
    with pytest.raises(KeyError):
        JOINT.geometry.slice("nope")


def test_features_shapes_and_points_rebuild_fea_nodes(episode):
    f = extract(episode, "ep")
    F, J, B = len(episode.t), len(episode.joint_xy), len(episode.beams)
    assert f.joint_state.shape == (F, J, JOINT.state_size) and f.beam_state.shape == (F, B, BEAM.state_size)
    assert f.joint_bc.shape == (J, JOINT.bc.size) and f.beam_bc.shape == (B, BEAM.bc.size)
    assert f.joint_bc[:, JOINT.bc.slice("fixed")].sum() == 1
    assert np.allclose(f.joint_state[0, episode.fixed_joint, JOINT.geometry.slice("center")], 0.0)
    assert len(f.point_nodes) == J * len(JOINT_POINTS) + B * len(BEAM_POINTS)
    pts = rebuild_all_points(f.joint_state, f.beam_state)
    assert np.abs(pts[0] - f.fea_points[0]).max() < 1e-4  # the flat reference is rebuilt exactly
    assert np.abs(pts - f.fea_points).max() < 0.02 * f.design_size
    # every beam end face shares its 4 corners and 2 edge middles with its joints (6 nodes per end)
    assert len(shared_point_pairs(f.point_nodes)) == B * 2 * 6


def test_welding_puts_each_shared_node_at_the_mean_of_its_copies_and_leaves_the_rest(episode):
    f = extract(episode, "ep")
    pts = rebuild_all_points(f.joint_state.astype(float), f.beam_state.astype(float))  # [F, P, 3]
    pairs = shared_point_pairs(f.point_nodes)
    rng = np.random.default_rng(1)
    torn = pts + rng.normal(scale=2.0, size=pts.shape)  # every block's copy of an interface off by its own error
    w = welded(torn, f.point_nodes)
    assert w.shape == torn.shape
    assert np.allclose(w[:, pairs[:, 0]], w[:, pairs[:, 1]])  # one position per node
    err = lambda p: np.linalg.norm(p - pts, axis=-1)  # noqa: E731
    sizes = []
    for node in np.unique(f.point_nodes[pairs.ravel()]):  # 2 copies on a face, 3 where two beams meet a joint corner
        copies = np.flatnonzero(f.point_nodes == node)
        sizes.append(len(copies))
        assert np.allclose(w[:, copies], torn[:, copies].mean(axis=1, keepdims=True))
        assert (err(w)[:, copies[0]] <= err(torn)[:, copies].max(axis=1) + 1e-9).all()  # within the copies' hull
    assert set(sizes) >= {2}
    alone = np.setdiff1d(np.arange(len(f.point_nodes)), pairs.ravel())
    assert len(alone) > 0 and np.array_equal(w[:, alone], torn[:, alone])
    assert np.allclose(welded(w, f.point_nodes), w)  # welding a welded answer changes nothing
    assert np.allclose(welded(torn[None], f.point_nodes)[0], w)  # any leading axes (ensemble members)


def test_stress_rotation_is_a_tensor_rotation():
    rng = np.random.default_rng(0)
    s = rng.normal(size=(5, 6))
    R = rotation_z(0.7)
    got = voigt_to_tensor(rotate_stress(s, R))
    want = R @ voigt_to_tensor(s) @ R.T
    assert np.allclose(got, want)
    assert np.allclose(np.trace(got, axis1=-2, axis2=-1), np.trace(voigt_to_tensor(s), axis1=-2, axis2=-1))


@pytest.mark.parametrize("angle", [0.3, np.pi / 2, 2.5])
def test_extract_then_rotate_equals_rotate_then_extract(episode, angle):
    R = rotation_z(angle)
    shifted = episode.node_xyz + np.array([12.0, -5.0, 0.0], np.float32)  # not about the fixed joint: translation too
    ep = episode.replace(node_xyz=shifted)
    rotated = ep.replace(node_xyz=(shifted.astype(np.float64) @ R.T).astype(np.float32),
                         stress=rotate_stress(ep.stress.astype(np.float64), R).astype(np.float32))
    a = extract(ep).rotated(R)
    b = extract(rotated)
    for name in ("joint_state", "beam_state", "joint_bc", "beam_bc", "fea_points"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=2e-4, err_msg=name)
    assert np.allclose(b.origin, R @ a.origin)
