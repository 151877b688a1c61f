"""learn.pca / gn / model: PCA retention and inversion, GN block shapes and permutation equivariance."""
import numpy as np
import pytest
import torch

from data_schema.testing import synthetic_episode
from learn.dataset import GraphSet, augment, split_names
from learn.features import extract
from learn.gn import GNBlock, sum_to
from learn.graph import BEAM, JOINT, Incidence, disjoint_union
from learn.model import TERMS, Simulator
from learn.pca import Normalizer, TermPCA

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def features():
    return [extract(synthetic_episode(3, 3, 5, 3, 3, 5, seed=s), name=f"ep{s}.h5") for s in range(6)]


def test_split_is_by_episode_and_pca_is_fitted_on_train_only(features):
    split = split_names(features, {"train": 0.6, "val": 0.2, "test": 0.2}, seed=0)
    names = [n for s in split.values() for n in s]
    assert sorted(names) == sorted(f.name for f in features) and len(set(names)) == len(names)
    assert all(split[s] for s in split)
    by_name = {f.name: f for f in features}
    train = GraphSet.build(augment([by_name[n] for n in split["train"]], rotations=4, seed=0))
    assert len(train) == 4 * len(split["train"])
    x = train.joint_state.reshape(-1, JOINT.state_size)[:, JOINT.stress_slice].numpy()
    pca = TermPCA.fit(x, retention=0.98)
    assert float(pca.explained) >= 0.98 and pca.k < x.shape[1]
    # statistics come from the training rows only: the mean equals theirs
    assert np.allclose(pca.mean.numpy(), x.mean(axis=0), atol=1e-6)
    z = pca(torch.as_tensor(x))
    assert torch.all(z >= pca.lo - 1e-5) and torch.all(z <= pca.hi + 1e-5)
    back = pca.inverse(z).numpy()
    rel = np.linalg.norm(back - x) / np.linalg.norm(x - x.mean(axis=0))
    assert rel < np.sqrt(0.02) + 1e-6  # at most the discarded 2 % of the variance


def test_extend_split_keeps_held_out_episodes_and_adds_new_ones_to_train(features):
    from learn.dataset import extend_split
    old = split_names(features[:4], {"train": 0.5, "val": 0.25, "test": 0.25}, seed=0)
    new = extend_split(old, [f.name for f in features])
    assert new["val"] == old["val"] and new["test"] == old["test"]
    assert sorted(new["train"]) == sorted(old["train"] + [f.name for f in features[4:]])
    with pytest.raises(FileNotFoundError, match="not in the data"):
        extend_split(old, [f.name for f in features[1:]])
    held = old["val"][0]  # split_missing=drop: a held-out episode the data lack is left out, the rest kept
    present = [f.name for f in features if f.name != held]
    dropped = extend_split(old, present, "drop")
    assert held not in sum(dropped.values(), []) and dropped["test"] == old["test"]
    assert sorted(sum(dropped.values(), [])) == sorted(present)
    with pytest.raises(ValueError, match="split_missing='skip': must be error | drop"):
        extend_split(old, present, "skip")


def test_pca_keeps_a_rare_flag_column():
    rng = np.random.default_rng(0)
    x = np.concatenate([(rng.random((900, 1)) < 0.1).astype(float), 50 * rng.normal(size=(900, 3))], axis=1)
    pca = TermPCA.fit(x, 0.98)
    back = pca.inverse(pca(torch.as_tensor(x, dtype=torch.float32))).numpy()
    assert np.abs(back[:, 0] - x[:, 0]).max() < 1e-3


def test_normalizer_floor():
    x = np.stack([np.zeros(10), np.arange(10.0)], axis=1)
    n = Normalizer.fit(x, floor=0.1)
    assert n.std[0] > 0 and torch.allclose(n.inverse(n(torch.as_tensor(x, dtype=torch.float32))),
                                           torch.as_tensor(x, dtype=torch.float32))


def _random_graph(seed=0):
    g = torch.Generator().manual_seed(seed)
    beams = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [0, 2]])
    inc = Incidence.from_beams(beams, 4)
    return inc, torch.randn(2, 4, 5, generator=g), torch.randn(2, 5, 7, generator=g), torch.randn(2, 10, 3, generator=g)


@pytest.mark.parametrize("global_latent", [0, 6])
def test_gn_block_shapes_and_permutation_equivariance(global_latent):
    torch.manual_seed(0)
    inc, xj, xb, xe = _random_graph()
    gn = GNBlock(joint_in=5, beam_in=7, edge_in=3, latent=8, widths=[16, 12], joint_out=4, beam_out=6,
                 global_latent=global_latent)
    oj, ob = gn(xj, xb, xe, inc.tensors())
    assert oj.shape == (2, 4, 4) and ob.shape == (2, 5, 6)
    pj, pb = np.array([2, 0, 3, 1]), np.array([4, 2, 0, 1, 3])  # new joint n is old pj[n]; new beam b is old pb[b]
    old_to_new = np.argsort(pj)
    beams = np.stack([inc.senders[:5], inc.receivers[:5]], 1)
    inc2 = Incidence.from_beams(old_to_new[beams[pb]], 4)
    edge_perm = np.concatenate([pb, pb + 5])
    oj2, ob2 = gn(xj[:, pj], xb[:, pb], xe[:, edge_perm], inc2.tensors())
    assert torch.allclose(oj2, oj[:, pj], atol=1e-5) and torch.allclose(ob2, ob[:, pb], atol=1e-5)


@pytest.mark.parametrize("widths,layer_norm", [([16, 12], False), ([16], True), ([], False)])
def test_gn_block_interactions_are_the_mlps_of_the_concatenated_pair(widths, layer_norm):
    """The per-node first layer (GNBlock.interactions) is the thesis' f_I(cat(X_beam, X_sender, X_receiver, X_edge))
    of every directed edge, written out here as that formula."""
    torch.manual_seed(0)
    inc, xj, xb, xe = _random_graph()
    g = inc.tensors()
    gn = GNBlock(joint_in=5, beam_in=7, edge_in=3, latent=8, widths=widths, joint_out=4, beam_out=6,
                 layer_norm=layer_norm)
    pair = torch.cat([xb[:, g.edge_beam], xj[:, g.senders], xj[:, g.receivers], xe], -1)
    to_joint_edges, to_beam_edges = gn.interactions(xj, xb, xe, g)
    assert to_joint_edges.shape == (2, 10, 8)
    assert torch.allclose(to_joint_edges, gn.joint_interaction(pair), atol=1e-5)
    assert torch.allclose(to_beam_edges, gn.beam_interaction(pair), atol=1e-5)
    loss = (to_joint_edges.sum() + to_beam_edges.sum())
    loss.backward()
    assert gn.joint_interaction[0].weight.grad.abs().sum() > 0 and gn.beam_interaction[0].weight.grad.abs().sum() > 0


@pytest.mark.parametrize("widths,layer_norm,dropout", [([16, 12], False, 0.0), ([16], False, 0.3), ([16], True, 0.0),
                                                  ([], False, 0.0)])
def test_interactions_received_are_the_sums_of_the_edges_messages(widths, layer_norm, dropout):
    """GNBlock.received (a linear last layer applied once per receiver, to the summed hidden layer) gives every
    joint and beam the sum of its edges' messages as GNBlock.interactions makes them, to float32 rounding, and the
    gradients of that sum; with a LayerNorm after the last layer or no hidden layer it sums the messages themselves.
    In training mode (dropout) both draw the same units when seeded alike."""
    torch.manual_seed(0)
    inc, xj, xb, xe = _random_graph()
    g = inc.tensors()
    gn = GNBlock(joint_in=5, beam_in=7, edge_in=3, latent=8, widths=widths, joint_out=4, beam_out=6,
                 layer_norm=layer_norm, dropout=dropout)
    with torch.no_grad():  # biases large enough that counting a receiver's edges wrongly shows
        for m in gn.modules():
            if isinstance(m, torch.nn.Linear):
                m.bias.normal_(0.0, 1.0)
    torch.manual_seed(1)
    to_joint_edges, to_beam_edges = gn.interactions(xj, xb, xe, g)
    torch.manual_seed(1)
    to_joints, to_beams = gn.received(xj, xb, xe, g)
    torch.testing.assert_close(to_joints, sum_to(to_joint_edges, g.receivers, 4), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(to_beams, sum_to(to_beam_edges, g.edge_beam, 5), atol=1e-5, rtol=1e-5)
    grads = [torch.autograd.grad(x.square().sum(), gn.joint_interaction[0].weight)[0]
             for x in (sum_to(to_joint_edges, g.receivers, 4), to_joints)]
    torch.testing.assert_close(grads[0], grads[1], atol=1e-4, rtol=1e-4)


def test_design_wide_vector_stays_within_its_design():
    """A block with a design-wide vector gives every design of a disjoint union what it gives that design alone
    (one graph per leading batch row), and it does reach beyond one hop: a joint far from a change sees it."""
    torch.manual_seed(0)
    gn = GNBlock(joint_in=5, beam_in=7, edge_in=3, latent=8, widths=[16, 12], joint_out=4, beam_out=6,
                 global_latent=6)
    inc_a, xj_a, xb_a, xe_a = _random_graph(1)
    chain = Incidence.from_beams(np.array([[0, 1], [1, 2], [2, 3], [3, 4]]), 5)
    g = torch.Generator().manual_seed(2)
    xj_b, xb_b, xe_b = (torch.randn(2, 5, 5, generator=g), torch.randn(2, 4, 7, generator=g),
                        torch.randn(2, 8, 3, generator=g))
    union, jo, bo = disjoint_union([inc_a, chain])
    edges_u = torch.cat([xe_a, xe_b], 1)  # the union lists design a's directed edges, then design b's
    oj, ob = gn(torch.cat([xj_a, xj_b], 1), torch.cat([xb_a, xb_b], 1), edges_u, union.tensors())
    for inc, xj, xb, xe, j, b in ((inc_a, xj_a, xb_a, xe_a, slice(0, 4), slice(0, 5)),
                                  (chain, xj_b, xb_b, xe_b, slice(4, 9), slice(5, 9))):
        alone_j, alone_b = gn(xj, xb, xe, inc.tensors())
        assert torch.allclose(oj[:, j], alone_j, atol=1e-5) and torch.allclose(ob[:, b], alone_b, atol=1e-5)
    moved = xj_b.clone()
    moved[:, 0] += 1.0  # joint 0 of the chain: joint 4 is four hops away
    far_before = gn(xj_b, xb_b, xe_b, chain.tensors())[0][:, 4]
    far_after = gn(moved, xb_b, xe_b, chain.tensors())[0][:, 4]
    assert (far_after - far_before).abs().max() > 1e-4
    plain = GNBlock(joint_in=5, beam_in=7, edge_in=3, latent=8, widths=[16, 12], joint_out=4, beam_out=6)
    assert torch.allclose(plain(xj_b, xb_b, xe_b, chain.tensors())[0][:, 4],
                          plain(moved, xb_b, xe_b, chain.tensors())[0][:, 4])  # one hop only without it


@pytest.mark.parametrize("core,bc_position", [("single_gn", "reference"), ("double_gn", "reference"),
                                              ("double_gn", "current"), ("epd", "reference")])
def test_simulator_step_shapes(features, core, bc_position):
    data = GraphSet.build(features[:2])
    model = Simulator.fit({"core": core, "latent": 8, "widths": [16, 8], "time_input": True,
                           "bc_position": bc_position}, data.joint_state, data.beam_state, data.static)
    assert set(model.pca) == set(TERMS)
    j, b = model.step(data.joint_state[:3], data.beam_state[:3], data.static, data.t[:3])
    assert j.shape == data.joint_state[:3].shape and b.shape == data.beam_state[:3].shape
    assert torch.isfinite(j).all() and torch.isfinite(b).all()
    if bc_position == "current":
        return  # the current position relative to the fixed joint is an input by design
    # translation invariance of the update: shifting every point field leaves dG unchanged
    shift = torch.tensor([5.0, -3.0, 1.0])
    js, bs = data.joint_state[:3].clone(), data.beam_state[:3].clone()
    for sl in JOINT.geometry.slices("point"):
        js[..., sl] += shift
    for sl in BEAM.geometry.slices("point"):
        bs[..., sl] += shift
    d1 = model(data.joint_state[:3], data.beam_state[:3], data.static, data.t[:3])
    d2 = model(js, bs, data.static, data.t[:3])
    assert torch.allclose(d1[0], d2[0], atol=1e-4) and torch.allclose(d1[1], d2[1], atol=1e-4)


def test_local_frames_are_orthonormal_and_rotations_invert(features):
    from learn import frames
    data = GraphSet.build(features[:1])
    for state, block in ((data.joint_state, JOINT), (data.beam_state, BEAM)):
        R = frames.frame(state, block)
        eye = torch.eye(3).expand(R.shape)
        assert torch.allclose(R.transpose(-1, -2) @ R, eye, atol=1e-5)
        assert torch.allclose(torch.linalg.det(R), torch.ones(R.shape[:-2]), atol=1e-5)
        back = frames.rotate_state(frames.rotate_state(state, block, R, True), block, R, False)
        assert torch.allclose(back, state, atol=1e-4)


def test_vectors_and_stresses_rotate_into_and_out_of_frames_as_tensors():
    """frames.rotate_vectors: R^T v into a frame, R v out of it; frames.rotate_stresses: R^T s R and R s R^T of the
    Voigt stresses (xx yy zz xy xz yz) as 3 x 3 tensors, at random 3-D frames and several stacked fields."""
    from scipy.spatial.transform import Rotation
    from learn import frames
    R = torch.as_tensor(Rotation.random(10, random_state=7).as_matrix()).reshape(2, 5, 3, 3)
    gen = torch.Generator().manual_seed(0)
    v = torch.randn(2, 5, 4 * 3, generator=gen, dtype=torch.float64)
    s = torch.randn(2, 5, 3 * 6, generator=gen, dtype=torch.float64)
    rows, cols = [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]

    def tensor(voigt):  # [..., 6] -> [..., 3, 3]
        t = voigt.new_zeros(*voigt.shape[:-1], 3, 3)
        t[..., rows, cols] = voigt
        t[..., cols, rows] = voigt
        return t

    vs = v.unflatten(-1, (4, 3))
    ts = tensor(s.unflatten(-1, (3, 6)))
    Rf = R[..., None, :, :]  # the same frame for every field of a block
    torch.testing.assert_close(frames.rotate_vectors(v, R, to_local=True).unflatten(-1, (4, 3)),
                               (Rf.transpose(-1, -2) @ vs[..., None])[..., 0])
    torch.testing.assert_close(frames.rotate_vectors(v, R, to_local=False).unflatten(-1, (4, 3)),
                               (Rf @ vs[..., None])[..., 0])
    torch.testing.assert_close(tensor(frames.rotate_stresses(s, R, to_local=True).unflatten(-1, (3, 6))),
                               Rf.transpose(-1, -2) @ ts @ Rf)
    torch.testing.assert_close(tensor(frames.rotate_stresses(s, R, to_local=False).unflatten(-1, (3, 6))),
                               Rf @ ts @ Rf.transpose(-1, -2))


@pytest.mark.parametrize("frame", ["local", "fixed"])
def test_rotated_frame_simulator_is_equivariant_to_rotations_about_z(features, frame):
    """Rotating a design about z (through the fixed joint) rotates its predicted next state the same way; with the
    design frame ("fixed") also when the rotated copy shares a batch (one disjoint graph) with the original."""
    from dataclasses import replace
    from learn.symmetry import rotation_z
    f = features[0]
    data = GraphSet.build([f])
    torch.manual_seed(0)
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16, 8], "frame": frame,
                           "pin_fixed_joint": True}, data.joint_state, data.beam_state, data.static)
    R = rotation_z(1.1)
    both = GraphSet.build([f, f.rotated(R)])
    with torch.no_grad():
        j, b = model.step(data.joint_state[:3], data.beam_state[:3], data.static, data.t[:3])
        jb, bb = model.step(both.joint_state[:3], both.beam_state[:3], both.static, both.t[:3])
    J, B = both.joint_offsets[1], both.beam_offsets[1]
    want = replace(f, joint_state=j.numpy(), beam_state=b.numpy()).rotated(R)
    scale = np.abs(want.joint_state).max()
    assert np.abs(jb[:, :J].numpy() - j.numpy()).max() < 1e-5 * scale  # the original, beside its rotated copy
    assert np.abs(jb[:, J:].numpy() - want.joint_state).max() < 1e-5 * scale
    assert np.abs(bb[:, B:].numpy() - want.beam_state).max() < 1e-5 * scale


@pytest.mark.parametrize("frame", ["local", "fixed"])
def test_a_rotated_frame_model_weighs_its_loss_by_the_global_columns_step_stds(features, frame, tmp_path):
    """The deltas' normalisers of a frame local / fixed model hold each column's step std in the blocks' frames;
    the loss and its noise read global columns, so they take the global step stds (Simulator.step_std), which a
    global model's deltas hold. A checkpoint saved before they existed loads with the deltas' (what it trained on)."""
    from learn import checkpoint
    data = GraphSet.build(features[:3])
    args = {"core": "double_gn", "latent": 8, "widths": [16, 8], "pin_fixed_joint": True}
    plain = Simulator.fit(args, data.joint_state, data.beam_state, data.static)
    turned = Simulator.fit({**args, "frame": frame}, data.joint_state, data.beam_state, data.static)
    for got, want in zip(turned.step_std(), (plain.joint_delta.std, plain.beam_delta.std)):
        torch.testing.assert_close(got, want)
    if frame == "local":  # in the blocks' own frames the columns' spreads are others (by a factor 4 and more here)
        ratio = turned.joint_delta.std / turned.step_std()[0]
        assert ratio.max() / ratio.min() > 4
    old = {k: v for k, v in turned.state_dict().items() if "_step." not in k}
    loaded = checkpoint.model_from({"model_args": turned.args, "state_dict": old})
    torch.testing.assert_close(loaded.step_std()[0], turned.joint_delta.std)


def test_design_frame_turns_with_the_fixed_joint_about_z_only(features):
    """frames.design_frame: one rotation about z per design, the same for all its blocks, turned by R when the
    design is turned by R."""
    from learn import frames
    from learn.symmetry import rotation_z
    f = features[0]
    both = GraphSet.build([f, f.rotated(rotation_z(0.7))])
    fixed = both.static.joint_bc[..., JOINT.bc.slice("fixed")]
    Rj, Rb = frames.design_frame(both.joint_state[0], fixed, both.index)
    J, B = both.joint_offsets[1], both.beam_offsets[1]
    assert Rj.shape == (both.index.n_joints, 3, 3) and Rb.shape == (both.index.n_beams, 3, 3)
    assert torch.allclose(Rj[:J], Rj[0].expand(J, 3, 3)) and torch.allclose(Rb[:B], Rj[0].expand(B, 3, 3))
    assert torch.allclose(Rj[J:], Rj[J].expand(len(Rj) - J, 3, 3))
    assert torch.allclose(Rj[0][2], torch.tensor([0.0, 0.0, 1.0])) and torch.allclose(Rj[0][:, 2], Rj[0][2])
    assert torch.allclose(Rj[J], torch.as_tensor(rotation_z(0.7), dtype=torch.float32) @ Rj[0], atol=1e-5)
    single = frames.design_frame(both.joint_state[0, :J], fixed[:J], GraphSet.build([f]).index)[0]
    assert torch.allclose(single, Rj[:J])


def test_unknown_frame_is_refused_with_the_allowed_values():
    with pytest.raises(ValueError, match="model.frame='body': must be one of global | local | fixed"):
        Simulator({"core": "single_gn", "latent": 8, "widths": [8], "frame": "body",
                   "pca": {t: [1, 1] for t in ("joint_geometry", "joint_stress", "joint_bc", "beam_geometry",
                                               "beam_stress", "beam_bc")}})


def test_input_floor_is_zero_with_every_component_and_grows_as_the_pca_drops_some(features):
    """input_geometry: each block's geometry as the network sees it (through its PCA and back). Keeping every
    component reproduces the points to round-off; dropping components loses shape, which evaluate reports."""
    from learn.model import static_from
    from learn.rollout import input_floor
    train = GraphSet.build(augment(features[:4], rotations=4, seed=0))
    args = {"core": "double_gn", "latent": 8, "widths": [16], "time_input": True, "pin_fixed_joint": True}
    floors = []
    for retention in (1.0, 0.9):
        model = Simulator.fit(args, train.joint_state, train.beam_state, train.static, retention)
        f = features[5]
        js, bs = torch.as_tensor(f.joint_state), torch.as_tensor(f.beam_state)
        seen_j, seen_b = model.input_geometry(js, bs, static_from(f.joint_bc, f.beam_bc, f.incidence))
        assert torch.equal(seen_j[..., JOINT.stress_slice], js[..., JOINT.stress_slice])  # stress untouched
        floors.append(input_floor(model, f).max() / f.design_size)
    assert floors[0] < 1e-5 < 1e-3 < floors[1]


def test_the_both_geometry_loss_is_the_columns_plus_the_weighted_point_term(features):
    """multistep_loss(geometry="both"): every state column as "columns" weighs it, and the point term of "points" on
    top at point_weight. Without the stress columns (stress_weight 0) "columns" is the geometry columns alone and
    "points" the point term alone, so both = columns + point_weight x points; an unknown geometry is refused."""
    from learn.metrics import multistep_loss
    train = GraphSet.build(features[:2])
    torch.manual_seed(0)
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16], "time_input": True},
                          train.joint_state, train.beam_state, train.static, 1.0)

    def loss(geometry, stress_weight=0.0, **kw):
        with torch.no_grad():
            return float(multistep_loss(model, train, 2, stress_weight=stress_weight, geometry=geometry, **kw))

    columns, points = loss("columns"), loss("points")
    assert columns > 0 and points > 0
    for w in (0.0, 1.0, 2.5):
        assert loss("both", point_weight=w) == pytest.approx(columns + w * points, rel=1e-5)
    assert loss("points", point_weight=0.0) == pytest.approx(points, rel=1e-6)  # "points" weighs its term 1 always
    # with the stress columns: both at weight 0 is the column loss, stress included
    assert loss("both", 0.1, point_weight=0.0) == pytest.approx(loss("columns", 0.1), rel=1e-6)
    with pytest.raises(ValueError, match="must be columns . points . both"):
        multistep_loss(model, train, 2, geometry="mesh")


def test_a_stopped_rollout_gradient_trains_each_step_from_the_state_the_model_reached(features):
    """multistep_loss(carry=0): the same loss value, and the gradient of step 2 is that of a single step from the
    (detached) state step 1 produced; carry=0.5 over two steps: the gradient is halfway between stopped and through
    (step 2's error reaches step 1 at half weight), the loss value the same."""
    from learn.metrics import multistep_loss
    train = GraphSet.build(features[:2])
    torch.manual_seed(0)
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16], "time_input": True},
                          train.joint_state, train.beam_state, train.static, 1.0)
    params = list(model.parameters())

    def grads(loss):
        return torch.cat([g.flatten() for g in torch.autograd.grad(loss, params)])

    h, S = 2, len(train.t) - 2
    through, half, stop = (multistep_loss(model, train, h, carry=c) for c in (1.0, 0.5, 0.0))
    assert torch.allclose(through, stop) and torch.allclose(half, stop)
    # by hand: step 1 from the FEA states, step 2 from step 1's output with its history cut
    j, b = train.joint_state[:S], train.beam_state[:S]
    total = torch.zeros(())
    for k in range(h):
        j, b = model.step(j.detach(), b.detach(), train.static, train.t[k:S + k])
        ej = (j - train.joint_state[k + 1:S + k + 1]) / model.joint_delta.std
        eb = (b - train.beam_state[k + 1:S + k + 1]) / model.beam_delta.std
        w_j = torch.ones(JOINT.state_size)
        w_b = torch.ones(BEAM.state_size)
        total = total + (w_j * ej ** 2).mean() + (w_b * eb ** 2).mean()
    g_stop = grads(stop)
    assert torch.allclose(g_stop, grads(total / h), atol=1e-6)
    g_through = grads(through)
    assert not torch.allclose(g_through, g_stop, atol=1e-6)
    assert torch.allclose(grads(half), (g_through + g_stop) / 2, atol=1e-6)


@pytest.mark.parametrize("update", ["additive", "kinematic", "direct"])
def test_rotation_averaged_answer_is_equivariant_and_keeps_the_design(features, update):
    """answer_unroll with n rotations: a design rotated by one of the group's angles gets the rotated answer
    (exactly, unlike the network alone); frame 0 is the design itself; n = 1 is the network alone."""
    from dataclasses import replace

    from learn.model import rollout_rotations_checked
    from learn.rollout import answer_unroll, rollout, unroll
    from learn.symmetry import rotation_z
    f = features[0]
    data = GraphSet.build(features[:4])
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16, 8], "pin_fixed_joint": True,
                           "update": update}, data.joint_state, data.beam_state, data.static).eval()
    torch.manual_seed(0)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.3 * torch.randn_like(p))  # a far-from-equivariant network
    R = rotation_z(np.pi / 2)
    net = [rollout(model, g, steps=4) for g in (f, f.rotated(R))]

    def gap(r):  # the answer for the rotated design vs the rotated answer, relative to the largest coordinate
        return np.abs(r[1].local_points - r[0].local_points @ R.T).max() / np.abs(r[0].local_points).max()
    net_gap = gap(net)
    model.answer_with(4)
    sym = [rollout(model, g, steps=4) for g in (f, f.rotated(R))]
    assert gap(sym) < 1e-5 < 1e-2 < net_gap  # relative to the largest coordinate (float32; an untrained net)
    np.testing.assert_allclose(sym[0].joint_states[0], f.joint_state[0], atol=1e-4)
    np.testing.assert_allclose(sym[0].beam_states[0], f.beam_state[0], atol=1e-4)
    want = replace(f, joint_state=sym[0].joint_states, beam_state=sym[0].beam_states).rotated(R)
    np.testing.assert_allclose(sym[1].joint_states, want.joint_state, atol=1e-5 * np.abs(want.joint_state).max())
    one = GraphSet.build([f])
    with torch.no_grad():
        a = answer_unroll(model.answer_with(1), one.joint_state[0], one.beam_state[0], one.static, one.t)
        b = unroll(model, one.joint_state[0], one.beam_state[0], one.static, one.t)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    for bad in (0, 2.5, "4", 65):
        with pytest.raises(ValueError, match="rollout_rotations"):
            rollout_rotations_checked(bad, "rollout_rotations")


@pytest.mark.parametrize("core", ["double_gn", "epd"])
def test_design_wide_simulator_steps_designs_apart_and_compiles(features, core):
    """global_latent > 0: a batch of designs (disjoint union, as in training) steps each design as if alone, and the
    traced rollout (one design, no membership index) gives the eager numbers."""
    from learn.rollout import compile_rollout, graph_inputs
    from learn.evaluate import eager_rollout
    data = GraphSet.build(features[:2])
    args = {"core": core, "latent": 8, "widths": [16, 8], "time_input": True, "global_latent": 5, "n_blocks": 3,
            "layer_norm": core == "epd"}
    model = Simulator.fit(args, data.joint_state, data.beam_state, data.static).eval()
    with torch.no_grad():
        j, b = model.step(data.joint_state[:2], data.beam_state[:2], data.static, data.t[:2])
        for i, f in enumerate(features[:2]):
            alone = GraphSet.build([f])
            ja, ba = model.step(alone.joint_state[:2], alone.beam_state[:2], alone.static, alone.t[:2])
            js, bs = slice(*data.joint_offsets[i:i + 2]), slice(*data.beam_offsets[i:i + 2])
            assert torch.allclose(j[:, js], ja, atol=1e-4) and torch.allclose(b[:, bs], ba, atol=1e-4)
        compiled = compile_rollout(model, features[0])
        got = compiled(*graph_inputs(features[1]))[2]
        assert torch.allclose(got, eager_rollout(model, features[1])(), atol=1e-3)
    with pytest.raises(ValueError, match="model.global_latent"):
        Simulator.fit({**args, "global_latent": -1}, data.joint_state, data.beam_state, data.static)


@pytest.mark.parametrize("n_blocks", [3, 4])
def test_encode_process_decode_reaches_n_blocks_hops_and_is_equivariant(n_blocks):
    """The processor passes one joint-beam-joint hop per block: on a chain, a change at joint 0 reaches joint 4
    (four hops) with 4 blocks and not with 3; relabelling joints and beams relabels the output."""
    from learn.model import EncodeProcessDecode
    torch.manual_seed(0)
    core = EncodeProcessDecode(5, 7, 3, 4, 6, latent=8, widths=[16], n_blocks=n_blocks)
    chain = Incidence.from_beams(np.array([[0, 1], [1, 2], [2, 3], [3, 4]]), 5)
    g = torch.Generator().manual_seed(2)
    xj, xb, xe = torch.randn(2, 5, 5, generator=g), torch.randn(2, 4, 7, generator=g), torch.randn(2, 8, 3, generator=g)
    moved = xj.clone()
    moved[:, 0] += 1.0
    change = (core(moved, xb, xe, chain.tensors())[0][:, 4] - core(xj, xb, xe, chain.tensors())[0][:, 4]).abs().max()
    assert (change > 1e-6) if n_blocks >= 4 else (change == 0)  # float32 round-off is ~1e-7 here
    inc, xj, xb, xe = _random_graph()
    oj, ob = core(xj, xb, xe, inc.tensors())
    pj, pb = np.array([2, 0, 3, 1]), np.array([4, 2, 0, 1, 3])
    beams = np.stack([inc.senders[:5], inc.receivers[:5]], 1)
    inc2 = Incidence.from_beams(np.argsort(pj)[beams[pb]], 4)
    oj2, ob2 = core(xj[:, pj], xb[:, pb], xe[:, np.concatenate([pb, pb + 5])], inc2.tensors())
    assert torch.allclose(oj2, oj[:, pj], atol=1e-5) and torch.allclose(ob2, ob[:, pb], atol=1e-5)


def test_model_core_and_block_count_are_checked(features):
    data = GraphSet.build(features[:1])
    args = {"core": "epd", "latent": 8, "widths": [16], "time_input": True}
    with pytest.raises(ValueError, match="model.n_blocks=0"):
        Simulator.fit({**args, "n_blocks": 0}, data.joint_state, data.beam_state, data.static)
    with pytest.raises(ValueError, match="model.core='gat'"):
        Simulator.fit({**args, "core": "gat"}, data.joint_state, data.beam_state, data.static)
    with pytest.raises(ValueError, match="model.activation='swish'"):
        Simulator.fit({**args, "activation": "swish"}, data.joint_state, data.beam_state, data.static)


@pytest.mark.parametrize("core", ["double_gn", "epd"])
def test_model_activation_is_every_hidden_nonlinearity(features, core):
    data = GraphSet.build(features[:1])
    model = Simulator.fit({"core": core, "latent": 8, "widths": [16, 8], "time_input": True, "activation": "silu"},
                          data.joint_state, data.beam_state, data.static)
    kinds = {type(m) for m in model.modules()}
    assert torch.nn.SiLU in kinds and torch.nn.ReLU not in kinds
    j, b = model.step(data.joint_state[:2], data.beam_state[:2], data.static, data.t[:2])
    assert torch.isfinite(j).all() and torch.isfinite(b).all()


def test_pca_and_normaliser_fits_in_row_blocks_equal_the_one_pass_formulas():
    """The fits pass over float64 row blocks (memory bounded however many rows); the statistics are the textbook
    ones computed on the whole array at once, to round-off, for blocks of any size."""
    from learn.pca import Normalizer, TermPCA
    rng = np.random.default_rng(0)
    x = (rng.normal(size=(1001, 5)) @ rng.normal(size=(5, 5)) + [3.0, -1.0, 0.0, 200.0, 0.5]).astype(np.float32)
    x[:, 2] = 1e-9 * rng.normal(size=1001)  # a near-constant column: its scale is floored
    x64 = x.astype(np.float64)
    mean, std = x64.mean(axis=0), x64.std(axis=0)
    scale = np.maximum(std, 1e-3 * np.sqrt(np.mean(x64 ** 2)))
    xs = (x64 - mean) / scale
    eigval = np.sort(np.linalg.eigvalsh(xs.T @ xs / len(xs)))[::-1]
    for rows in (7, 1000, 1 << 18):
        p = TermPCA.fit(x, retention=1.0, rows=rows)
        np.testing.assert_allclose(p.mean.numpy(), mean, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(p.scale.numpy(), scale, rtol=1e-5)
        assert p.k == 4  # every component with variance (the near-constant column has none)
        np.testing.assert_allclose(p.sigma.numpy() ** 2, np.maximum(eigval[:4], 0.05 ** 2), rtol=1e-5)
        z = p(torch.as_tensor(x64, dtype=p.components.dtype)).numpy()
        np.testing.assert_allclose(p.lo.numpy(), z.min(axis=0), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(p.hi.numpy(), z.max(axis=0), rtol=1e-4, atol=1e-4)
        n = Normalizer.fit(x, rows=rows)
        np.testing.assert_allclose(n.mean.numpy(), mean, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(n.std.numpy(), np.maximum(std, 1e-6), rtol=1e-5)


def test_moments_merged_block_by_block_are_the_moments_of_all_rows():
    """Moments.add (Chan's pairwise merge) over blocks of any size gives the mean and covariance of all the rows at
    once, to float64 round-off relative to the data, even for a column whose mean is 1e6 times its spread (the
    naive sum-of-squares formula loses it)."""
    from learn.pca import Moments
    rng = np.random.default_rng(1)
    x = rng.normal(size=(500, 4)) @ rng.normal(size=(4, 4)) + [0.0, 5.0, -2.0, 1e6]
    for blocks in ([500], [1] * 500, [3, 0, 250, 247], [499, 1]):
        m, start = Moments(4), 0
        for b in blocks:
            m.add(x[start:start + b])
            start += b
        assert m.n == 500
        np.testing.assert_allclose(m.mean, x.mean(axis=0), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(m.cov, np.cov(x.T, bias=True), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(m.std, x.std(axis=0), rtol=1e-9)


@pytest.mark.parametrize("stress_input", [True, False])
def test_without_stress_input_the_update_does_not_read_the_stress(features, stress_input):
    data = GraphSet.build(features[:2])
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16, 8], "time_input": True,
                           "global_latent": 4, "stress_input": stress_input},
                          data.joint_state, data.beam_state, data.static)
    joints, beams, _ = model.encode(data.joint_state[:3], data.beam_state[:3], data.static, data.t[:3])
    stress_k = (model.pca["joint_stress"].k, model.pca["beam_stress"].k)
    full = sum(model.pca[t].k for t in TERMS[:3]) + 1, sum(model.pca[t].k for t in TERMS[3:]) + 1
    assert (joints.shape[-1], beams.shape[-1]) == (full if stress_input else
                                                   (full[0] - stress_k[0], full[1] - stress_k[1]))
    js, bs = data.joint_state[:3].clone(), data.beam_state[:3].clone()
    js[..., JOINT.stress_slice] *= 3.0  # another stress field, the same geometry
    bs[..., BEAM.stress_slice] *= 3.0
    d1 = model(data.joint_state[:3], data.beam_state[:3], data.static, data.t[:3])
    d2 = model(js, bs, data.static, data.t[:3])
    same = torch.allclose(d1[0], d2[0], atol=1e-6) and torch.allclose(d1[1], d2[1], atol=1e-6)
    assert same != stress_input  # read back only with stress_input
    j, b = model.step(data.joint_state[:3], data.beam_state[:3], data.static, data.t[:3])
    assert not torch.allclose(j[..., JOINT.stress_slice], data.joint_state[:3][..., JOINT.stress_slice])  # predicted


def test_dropout_acts_while_training_only_and_changes_nothing_when_off(features):
    """model.dropout > 0: two training-mode steps of the same input differ (units are dropped); in eval mode the step
    is the same network without dropout and the traced rollout gives the eager numbers; dropout 0 adds no layer
    (checkpoints written before the option load unchanged); values outside [0, 1) are refused naming the field."""
    from learn.evaluate import eager_rollout
    from learn.rollout import compile_rollout, graph_inputs
    data = GraphSet.build(features[:2])
    args = {"core": "double_gn", "latent": 8, "widths": [16, 8], "time_input": True, "global_latent": 4,
            "activation": "silu"}
    torch.manual_seed(0)
    off = Simulator.fit(args, data.joint_state, data.beam_state, data.static)
    torch.manual_seed(0)
    on = Simulator.fit({**args, "dropout": 0.3}, data.joint_state, data.beam_state, data.static)
    assert not any(isinstance(m, torch.nn.Dropout) for m in off.modules())
    assert sum(isinstance(m, torch.nn.Dropout) for m in on.modules()) > 0
    x = (data.joint_state[:2], data.beam_state[:2], data.static, data.t[:2])
    on.train()
    with torch.no_grad():
        a, b = on.step(*x)[0], on.step(*x)[0]
    assert not torch.allclose(a, b)
    on.eval(), off.eval()
    with torch.no_grad():  # the same seed draws the same weights (Dropout draws none): eval mode is the plain network
        a, b = on.step(*x)[0], on.step(*x)[0]
        assert torch.equal(a, b) and torch.allclose(a, off.step(*x)[0], atol=1e-6)
        got = compile_rollout(on, features[1])(*graph_inputs(features[1]))[2]
        assert torch.allclose(got, eager_rollout(on, features[1])(), atol=1e-3)
    for bad in (-0.1, 1.0, "0.2", True):
        with pytest.raises(ValueError, match="model.dropout"):
            Simulator.fit({**args, "dropout": bad}, data.joint_state, data.beam_state, data.static)


@pytest.mark.parametrize("frame", ["global", "fixed"])
def test_direct_update_answers_every_frame_from_the_design_alone(features, frame):
    """model.update=direct: G(t) = G(0) + dG(G(0), t). Frame 0 is the design; each frame is the same whatever other
    frames are asked for (nothing is fed back), in one batched pass or one at a time; the normalisers are fitted on
    the displacements from frame 0; the fixed joint stays put; the traced rollout gives the eager numbers; the loss
    has no horizon; without the time input it is refused."""
    from learn.evaluate import eager_rollout
    from learn.metrics import multistep_loss
    from learn.rollout import compile_rollout, graph_inputs, unroll
    data = GraphSet.build(features[:3])
    args = {"core": "double_gn", "latent": 8, "widths": [16, 8], "time_input": True, "global_latent": 4,
            "pin_fixed_joint": True, "update": "direct", "frame": frame}
    model = Simulator.fit(args, data.joint_state, data.beam_state, data.static).eval()
    if frame == "global":  # the updates it answers: displacements from the design, every frame
        d = (data.joint_state[1:] - data.joint_state[:1]).reshape(-1, JOINT.state_size)
        assert torch.allclose(model.joint_delta.mean, d.mean(0), atol=1e-4 * float(d.abs().max()))
    j0, b0, t = data.joint_state[0], data.beam_state[0], data.t
    with torch.no_grad():
        js, bs = unroll(model, j0, b0, data.static, t)
        assert js.shape == data.joint_state.shape and bs.shape == data.beam_state.shape
        assert torch.equal(js[0], j0) and torch.equal(bs[0], b0)
        for k in (1, len(t) - 1):  # frame k alone, asked for without the frames before it
            jk, bk = unroll(model, j0, b0, data.static, t[[0, k]])
            assert torch.allclose(jk[1], js[k], atol=1e-4) and torch.allclose(bk[1], bs[k], atol=1e-4)
        fixed = data.static.joint_bc[:, JOINT.bc.slice("fixed")][:, 0] > 0.5
        G = JOINT.geometry_slice
        assert torch.equal(js[:, fixed, G], j0[None, fixed, G].expand(len(t), -1, -1))
        losses = {h: float(multistep_loss(model, data, h)) for h in (1, 3, 10)}
        assert losses[1] == pytest.approx(losses[10]) == pytest.approx(losses[3])
        compiled = compile_rollout(model, features[0])
        assert torch.allclose(compiled(*graph_inputs(features[1]))[2], eager_rollout(model, features[1])(),
                              atol=1e-3)
    model.train()
    loss = multistep_loss(model, data, 10)
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
    with pytest.raises(ValueError, match="model.update=direct needs model.time_input=true"):
        Simulator.fit({**args, "time_input": False}, data.joint_state, data.beam_state, data.static)


def test_beam_spans_are_the_grids_span_along_each_beam_over_across_it_and_every_copy_reads_the_same(features):
    from learn.model import beam_spans, static_from
    from learn.symmetry import rotation_z
    # a 3 x 3 rectangle, 100 mm between columns and 50 between rows, fixed at the centre: a beam along i spans 200 mm
    # of its grid along itself and 100 across, one along j the reverse
    ij = [(i, j) for j in range(3) for i in range(3)]
    position = np.array([[100.0 * (i - 1), 50.0 * (j - 1), 0.0] for i, j in ij])
    joint_bc = np.concatenate([np.zeros((9, 1)), position], 1)
    beams = [(3 * j + i, 3 * j + i + 1) for j in range(3) for i in range(2)] + \
            [(3 * j + i, 3 * j + i + 3) for j in range(2) for i in range(3)]
    g = Incidence.from_beams(np.array(beams), 9).tensors()
    spans = beam_spans(torch.as_tensor(joint_bc, dtype=torch.float64), g)[:, 0]
    np.testing.assert_allclose(spans.numpy(), [np.log(2.0)] * 6 + [-np.log(2.0)] * 6, atol=1e-12)
    # turned, mirrored, relabelled: the same number per beam; two designs as one graph: each its own
    f = features[0]
    want = beam_spans(static_from(f.joint_bc, f.beam_bc, f.incidence).joint_bc, f.incidence.tensors())
    for copy in (f.rotated(rotation_z(0.7)), f.mirrored(), f.half_turned(), f.quarter_turned()):
        got = beam_spans(static_from(copy.joint_bc, copy.beam_bc, copy.incidence).joint_bc, copy.incidence.tensors())
        torch.testing.assert_close(got, want, atol=1e-5, rtol=0)
    data = GraphSet.build(features[:3])
    alone = [beam_spans(static_from(x.joint_bc, x.beam_bc, x.incidence).joint_bc, x.incidence.tensors())
             for x in features[:3]]
    torch.testing.assert_close(data.static.beam_spans(), torch.cat(alone), atol=1e-6, rtol=0)
    assert data.static.beam_spans().abs().max() > 0.01  # the synthetic designs are not all square


def test_a_span_input_model_reads_the_spans_and_compiles(features):
    from learn.evaluate import eager_rollout
    from learn.rollout import compile_rollout, graph_inputs
    data = GraphSet.build(features[:3])
    args = {"core": "double_gn", "latent": 8, "widths": [16, 8], "pin_fixed_joint": True, "global_latent": 4}
    torch.manual_seed(0)
    model = Simulator.fit({**args, "span_input": True}, data.joint_state, data.beam_state, data.static).eval()
    plain = Simulator.fit(args, data.joint_state, data.beam_state, data.static)
    assert model.core.blocks[0].beam_update[0].in_features == plain.core.blocks[0].beam_update[0].in_features + 1
    with torch.no_grad():
        j, b = model.step(data.joint_state[:1], data.beam_state[:1], data.static, data.t[:1])
        for layer in model.core.modules():  # make the spans matter, then change them: the step changes
            if isinstance(layer, torch.nn.Linear):
                layer.weight.add_(0.05)
        before = model.step(data.joint_state[:1], data.beam_state[:1], data.static, data.t[:1])[1]
        data.static.spans = data.static.beam_spans() + 1.0
        after = model.step(data.joint_state[:1], data.beam_state[:1], data.static, data.t[:1])[1]
        assert (after - before).abs().max() > 1e-4
        data.static.spans = None
        compiled = compile_rollout(model, features[0])
        torch.testing.assert_close(compiled(*graph_inputs(features[1]))[2], eager_rollout(model, features[1])(),
                                   atol=1e-3, rtol=1e-4)
