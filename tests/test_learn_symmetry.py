"""The mirror (learn.symmetry.MIRROR, EpisodeFeatures.mirrored) against the FEA of a mirrored design, and the
group-averaged answers (learn.rollout.answer_unroll) it enables."""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from data_schema.episode import read_episode
from data_schema.testing import synthetic_episode
from learn.dataset import GraphSet, TurnedSet, augment, augment_angles, labelled
from learn.features import extract, rebuild_all_points
from learn.graph import BEAM
from learn.model import Simulator
from learn.rollout import rollout

ROOT = Path(__file__).resolve().parent.parent
KINDS = ("up", "down", "passive")


def design_3x3(labelling: str = "plain") -> dict:
    """A jittered 3x3 design with mixed actuators, labelled as the factory labels it (beams run towards +i or +j).
    mirror: x <-> y and lattice (i, j) -> (j, i); half_turn: the same design, lattice (i, j) -> (2 - i, 2 - j), so
    every beam runs the other way; quarter_turn: the same design, lattice (i, j) -> (j, 2 - i), so the beams along i
    run the other way."""
    rng = np.random.default_rng(7)
    joints, index = [], {}
    for j in range(3):
        for i in range(3):
            index[i, j] = len(joints)
            x, y = 75.0 * i + rng.uniform(-8, 8), 60.0 * j + rng.uniform(-8, 8)
            ij, xy = {"plain": ([i, j], [x, y]), "mirror": ([j, i], [y, x]),
                      "half_turn": ([2 - i, 2 - j], [x, y]), "quarter_turn": ([j, 2 - i], [x, y])}[labelling]
            joints.append({"ij": ij, "xy": xy})
    beams = [[index[i, j], index[i + 1, j]] for j in range(3) for i in range(2)] + \
            [[index[i, j], index[i, j + 1]] for j in range(2) for i in range(3)]
    reversed_beams = {"half_turn": range(12), "quarter_turn": range(6)}.get(labelling, ())  # 0-5: along i
    beams = [[b, a] if n in reversed_beams else [a, b] for n, (a, b) in enumerate(beams)]
    beams = [[a, b, KINDS[n % 3]] for n, (a, b) in enumerate(beams)]
    return {"format": "morphsim.design/1", "joints": joints, "beams": beams, "fixed_joint": index[1, 1],
            "beam_width": 7.2, "thickness": 4.0, "meta": {"family": "random"}}


def solved(tmp_path: Path, labelling: str):
    design, out = tmp_path / f"d_{labelling}.json", tmp_path / f"e_{labelling}.h5"
    design.write_text(json.dumps(design_3x3(labelling)))
    r = subprocess.run([sys.executable, "-m", "fea_factory.solve", f"design={design}", f"out={out}", "mesh=coarse"],
                       cwd=ROOT, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-1000:] + r.stderr[-2000:]
    return extract(read_episode(out))


def assert_same_features(m, g):
    """Every field of two EpisodeFeatures equal to float32 round-off of their scale."""
    assert g.incidence.n_beams == m.incidence.n_beams and (g.incidence.senders == m.incidence.senders).all()
    assert (g.incidence.receivers == m.incidence.receivers).all()
    tol = lambda x: 1e-5 * max(1.0, np.abs(x).max())  # noqa: E731  float32 features
    for name in ("joint_state", "beam_state", "joint_bc", "beam_bc", "fea_points"):
        np.testing.assert_allclose(getattr(m, name), getattr(g, name), atol=tol(getattr(g, name)), err_msg=name)


@pytest.fixture(scope="module")
def plain_fea(tmp_path_factory):
    pytest.importorskip("dolfinx")
    return solved(tmp_path_factory.mktemp("plain"), "plain")


def test_mirrored_features_are_the_fea_of_the_mirrored_design(plain_fea, tmp_path):
    """Physics is mirror-symmetric (isotropic material and joint stress, beams printed along/across their axis,
    gravity along z), so the FEA of the mirrored design equals the mirrored features to round-off, in every frame."""
    f, g = plain_fea, solved(tmp_path, "mirror")
    assert_same_features(f.mirrored(), g)
    # the plain reflection without relabelling is far off: the labels matter
    swap_xy = [3 * k + c for k in range(BEAM.geometry.size // 3) for c in (1, 0, 2)]
    naive = f.beam_state[..., BEAM.geometry_slice][..., swap_xy]
    assert np.abs(naive - g.beam_state[..., BEAM.geometry_slice]).max() > 1.0


@pytest.mark.parametrize("labelling", ["half_turn", "quarter_turn"])
def test_lattice_turned_features_are_the_fea_of_the_design_labelled_from_another_corner(plain_fea, tmp_path,
                                                                                       labelling):
    """Relabelling the lattice from another corner moves nothing, so its FEA is the same solution: the beams that
    now run the other way reversed, every joint's corners turned (EpisodeFeatures.half_turned, quarter_turned), to
    round-off in every frame."""
    f, g = plain_fea, solved(tmp_path, labelling)
    assert_same_features(f.half_turned() if labelling == "half_turn" else f.quarter_turned(), g)
    assert np.abs(f.beam_state - g.beam_state).max() > 1.0  # and the labels matter


def test_mirror_is_an_involution_and_keeps_points_and_shared_nodes():
    f = extract(synthetic_episode(3, 3, 5, 3, 3, frames=3))
    back = f.mirrored().mirrored()
    for name in ("joint_state", "beam_state", "joint_bc", "beam_bc", "fea_points", "point_nodes", "origin"):
        np.testing.assert_allclose(getattr(back, name), getattr(f, name), atol=1e-5, err_msg=name)
    m = f.mirrored()  # the points its features rebuild are the mirrored FEA points (flat frame: exactly)
    np.testing.assert_allclose(rebuild_all_points(m.joint_state[0].astype(float), m.beam_state[0].astype(float)),
                               m.fea_points[0], atol=1e-4)
    assert len(augment([f], rotations=3, seed=0, mirror=True)) == 6


def test_lattice_turns_relabel_and_keep_the_points():
    f = extract(synthetic_episode(3, 3, 5, 3, 3, frames=3))
    h = f.half_turned()
    back = h.half_turned()
    for name in ("joint_state", "beam_state", "joint_bc", "beam_bc", "fea_points", "point_nodes", "origin"):
        np.testing.assert_allclose(getattr(back, name), getattr(f, name), atol=1e-5, err_msg=name)
    assert (back.incidence.senders == f.incidence.senders).all()
    rebuilt = lambda e: rebuild_all_points(e.joint_state.astype(float), e.beam_state.astype(float))  # noqa: E731
    np.testing.assert_allclose(rebuilt(h)[0], h.fea_points[0], atol=1e-4)  # flat frame: exactly the FEA points
    for a, b in ((rebuilt(h), rebuilt(f)), (h.fea_points, f.fea_points)):  # the same points in a relabelled order
        np.testing.assert_allclose(np.sort(a, axis=-2), np.sort(b, axis=-2), atol=1e-4)
    B = f.incidence.n_beams
    assert (h.incidence.senders[:B] == f.incidence.receivers[:B]).all()
    q = f.quarter_turned()  # a group: four quarter turns are none, two are the half turn
    np.testing.assert_array_equal(q.quarter_turned().beam_state, h.beam_state)
    np.testing.assert_array_equal(q.quarter_turned().quarter_turned().quarter_turned().joint_state, f.joint_state)
    assert f.beams_along_i().sum() == 6 and (q.beams_along_i() == ~f.beams_along_i()).all()
    copies = augment([f], rotations=3, seed=0, mirror=True, lattice_turns=4)
    assert len(copies) == 24 and len({c.incidence.senders[0] for c in copies}) == 2
    assert [len(augment([f], 1, 0, lattice_turns=n)) for n in (1, 2, 4)] == [1, 2, 4]


def test_mirror_averaged_answer_is_mirror_equivariant():
    fs = [extract(synthetic_episode(3, 3, 5, 3, 3, 5, seed=s)) for s in range(3)]
    data = GraphSet.build(fs)
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16, 8], "pin_fixed_joint": True},
                          data.joint_state, data.beam_state, data.static).eval()
    torch.manual_seed(0)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.3 * torch.randn_like(p))
    f = fs[0]
    scale = lambda r: np.abs(r.local_points).max()  # noqa: E731

    def gap(a, b):  # the answer for the mirrored design vs the mirrored answer
        want = replace(f, joint_state=a.joint_states, beam_state=a.beam_states).mirrored()
        return np.abs(b.joint_states - want.joint_state).max() / np.abs(want.joint_state).max()
    plain = gap(rollout(model, f, steps=4), rollout(model, f.mirrored(), steps=4))
    model.answer_with(2, True)
    a, b = rollout(model, f, steps=4), rollout(model, f.mirrored(), steps=4)
    assert gap(a, b) < 1e-5 < 1e-2 < plain and scale(a) > 0
    np.testing.assert_allclose(a.joint_states[0], f.joint_state[0], atol=1e-4)
    with pytest.raises(ValueError, match="rollout_mirror"):
        model.answer_with(None, "yes")


@pytest.mark.parametrize("turns, relabel", [(2, "half_turned"), (4, "quarter_turned"), (4, "half_turned")])
def test_lattice_averaged_answer_is_equivariant_to_relabelling(turns, relabel):
    """Averaged over the lattice labellings (model.rollout_lattice_turns), the answer for the design labelled from
    another corner is the relabelled answer: what a designer gets does not depend on which corner the lattice is
    numbered from. The network alone (1 labelling) answers differently; with the mirror and rotations on top, too."""
    fs = [extract(synthetic_episode(3, 3, 5, 3, 3, 5, seed=s)) for s in range(3)]
    data = GraphSet.build(fs)
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16, 8], "pin_fixed_joint": True,
                           "global_latent": 8}, data.joint_state, data.beam_state, data.static).eval()
    torch.manual_seed(0)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.3 * torch.randn_like(p))
    f = fs[1]

    def gap():  # the answer for the relabelled design vs the relabelled answer
        a, b = rollout(model, f, steps=4), rollout(model, getattr(f, relabel)(), steps=4)
        want = getattr(replace(f, joint_state=a.joint_states, beam_state=a.beam_states), relabel)()
        return max(np.abs(got - w).max() / np.abs(w).max()
                   for got, w in ((b.joint_states, want.joint_state), (b.beam_states, want.beam_state)))
    plain = gap()
    model.answer_with(rollout_lattice_turns=turns)
    averaged = gap()
    model.answer_with(2, True)
    with_group = gap()
    assert max(averaged, with_group) < 1e-5 < 1e-2 < plain
    a = rollout(model, f, steps=4)  # frame 0 is the design itself
    np.testing.assert_allclose(a.beam_states[0], f.beam_state[0], atol=1e-4)
    with pytest.raises(ValueError, match="rollout_lattice_turns=3: must be one of"):
        model.answer_with(rollout_lattice_turns=3)


def test_a_graph_set_turned_per_item_equals_the_set_of_turned_designs():
    """GraphSet.rotated (the per-batch rotations of rotations_redraw) turns each item's states and bc terms as
    EpisodeFeatures.rotated does, item by item; batches with rotations hold every item that many times."""
    from learn.symmetry import rotation_z
    fs = [extract(synthetic_episode(3, 3, 5, 3, 3, 5, seed=s), name=f"ep{s}.h5") for s in (1, 2)]
    angles = [0.4, -2.0]
    got = GraphSet.build(fs).rotated(angles)
    want = GraphSet.build([f.rotated(rotation_z(a)) for f, a in zip(fs, angles)])
    for a, b in ((got.joint_state, want.joint_state), (got.beam_state, want.beam_state),
                 (got.static.joint_bc, want.static.joint_bc), (got.static.beam_bc, want.static.beam_bc)):
        assert torch.allclose(a, b, atol=1e-4 * float(b.abs().max()))
    batches = list(GraphSet.build(fs).batches(3, torch.Generator().manual_seed(0), rotations=4))
    assert sorted(len(b) for b in batches) == [2, 3, 3] and sorted(i.name for b in batches for i in b.items) == \
        ["ep1.h5"] * 4 + ["ep2.h5"] * 4
    first = [b.joint_state[0, b.joint_offsets[k]:b.joint_offsets[k + 1]] for b in batches
             for k, i in enumerate(b.items) if i.name == "ep1.h5"]  # its four copies, each turned its own way
    assert all(not torch.allclose(x, y, atol=1e-3) for n, x in enumerate(first) for y in first[n + 1:])


def test_a_turned_set_gives_the_stored_sets_batches_at_a_fraction_of_the_memory():
    """rotations_stored=false: the copies turned per batch (TurnedSet) are the stored augmented set's, batch for
    batch in the same shuffled order, to float32 round-off; turned_copies is the whole stored set."""
    fs = [extract(synthetic_episode(3, 3, 5, 3, 3, 5, seed=s), name=f"ep{s}.h5") for s in (1, 2, 3)]
    rotations, seed = 4, 7
    stored = GraphSet.build(augment(fs, rotations, seed, mirror=True, lattice_turns=2))
    base = GraphSet.build(labelled(fs, mirror=True, lattice_turns=2))
    turned = TurnedSet(base, augment_angles(len(base), rotations, seed))
    assert len(turned) == len(stored) == 3 * 2 * 2 * rotations
    close = lambda a, b: torch.allclose(a, b, atol=1e-5 * float(b.abs().max()))  # noqa: E731
    whole = base.turned_copies(turned.angles)
    assert close(whole.joint_state, stored.joint_state) and close(whole.beam_state, stored.beam_state)
    assert close(whole.static.beam_bc, stored.static.beam_bc) and close(whole.static.joint_bc, stored.static.joint_bc)
    got = list(turned.batches(5, torch.Generator().manual_seed(3)))
    want = list(stored.batches(5, torch.Generator().manual_seed(3)))
    assert [len(b) for b in got] == [len(b) for b in want] and len(got) == 10
    for g, w in zip(got, want):
        assert [i.name for i in g.items] == [i.name for i in w.items]
        assert close(g.joint_state, w.joint_state) and close(g.beam_state, w.beam_state)
        assert close(g.static.beam_bc, w.static.beam_bc) and torch.equal(g.index.senders, w.index.senders)
    with pytest.raises(ValueError, match="rotations_redraw"):
        turned.batches(5, torch.Generator(), rotations=4)


def test_the_fit_over_turned_blocks_is_the_fit_over_the_stored_set():
    """rotations_stored=false fits the PCA and normalisers a block of turned copies at a time
    (TurnedSet.fit_blocks -> Simulator.fit_blocks), never holding every copy's terms: the normalisers, the PCA's
    means, scales and spectrum (and the covariance it keeps) equal the fit on the whole stored set to float32
    round-off of the turned states, and each fit's coefficient range is exactly its data's."""
    fs = [extract(synthetic_episode(3, 3, 5, 3, 3, 5, seed=s), name=f"ep{s}.h5") for s in (1, 2, 3)]
    base = GraphSet.build(labelled(fs, mirror=True, lattice_turns=2))
    turned = TurnedSet(base, augment_angles(len(base), 4, 7))
    stored = base.turned_copies(turned.angles)
    args = {"core": "double_gn", "latent": 8, "widths": [16, 8], "pin_fixed_joint": True}
    whole = Simulator.fit(args, stored.joint_state, stored.beam_state, stored.static, 1.0)
    for size in (4, 9, 1000):  # one item's 4 copies per block, 2 items per block, everything at once
        blocks = turned.fit_blocks(size)
        per = max(size // 4, 1)  # items per block; each item's 4 turned copies, 9 joints each
        assert [j.shape[1] // 9 for j, _, _ in blocks()] == [4 * min(per, len(base) - s)
                                                           for s in range(0, len(base), per)]
        fitted = Simulator.fit_blocks(args, blocks, 1.0)
        for name in ("edge_norm", "joint_delta", "beam_delta"):
            for stat in ("mean", "std"):
                a, b = getattr(getattr(fitted, name), stat), getattr(getattr(whole, name), stat)
                assert torch.allclose(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max())), (size, name, stat)
        for t, p in fitted.pca.items():
            q = whole.pca[t]
            assert p.k == q.k, t
            assert torch.allclose(p.mean, q.mean, rtol=1e-4, atol=1e-5 * float(q.mean.abs().max() + 1e-6)), t
            assert torch.allclose(p.scale, q.scale, rtol=1e-4), t
            assert torch.allclose(p.sigma, q.sigma, rtol=1e-3, atol=1e-4), t
            kept = lambda m: (m.components * m.sigma ** 2) @ m.components.T  # noqa: E731
            assert torch.allclose(kept(p), kept(q), atol=1e-3 * float(kept(q).abs().max())), t
            raw = fitted.raw_terms(stored.joint_state, stored.beam_state, stored.static)[t]
            z = p(raw.reshape(-1, raw.shape[-1]))
            assert torch.allclose(p.lo, z.min(dim=0).values, atol=1e-4) and torch.allclose(p.hi, z.max(dim=0).values,
                                                                                            atol=1e-4), t
