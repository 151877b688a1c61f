"""learn.rollout.rollout_many (GraphSet.first_frames): designs rolled out together as one disjoint union get their
answers alone."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from data_schema.testing import synthetic_episode
from learn.dataset import GraphSet
from learn.ensemble import Ensemble
from learn.features import extract
from learn.model import Simulator
from learn.rollout import compile_rollout, graph_inputs, rollout, rollout_many

torch.set_num_threads(1)

MODELS = {  # the default (local-frame stiffness), the thesis' additive update, a tree-placed one, a design-wide vector
    "local stiffness": {"update": "stiffness", "frame": "local", "stress_input": False},
    "additive": {"update": "additive"},
    "kinematic": {"update": "kinematic", "frame": "local"},
    "design-wide": {"update": "additive", "global_latent": 4, "span_input": True},
}


@pytest.fixture(scope="module")
def features():
    """Designs of different sizes and fixed joints (a batch need not be of one shape)."""
    shapes = [(3, 3), (2, 3), (3, 3), (3, 2)]
    return [extract(synthetic_episode(nx, ny, 5, 3, 3, 5, seed=s), name=f"ep{s}.h5") for s, (nx, ny) in
            enumerate(shapes)]


def fitted(features, options: dict, seed: int = 0) -> Simulator:
    data = GraphSet.build(features)
    torch.manual_seed(seed)  # the initial weights too: a test's network must not depend on the tests run before it
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16, 8], "pin_fixed_joint": True, **options},
                          data.joint_state, data.beam_state, data.static).eval()
    torch.manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))  # a network that says something, so that crosstalk would show
    return model


@pytest.mark.parametrize("kind", sorted(MODELS))
def test_designs_rolled_out_together_get_the_answers_they_get_alone(features, kind):
    """rollout_many over designs of three shapes: every design's states and points are those of its own rollout
    (float32 rounding apart: 1e-4 of the largest coordinate), with symmetry copies too; a design's answer does not
    depend on which designs share its batch (the first design alone vs with three others)."""
    model = fitted(features, MODELS[kind])
    if kind == "local stiffness":
        model.answer_with(rollout_mirror=True, rollout_lattice_turns=2)  # copies as a second union inside the first
    alone = [rollout(model, f, steps=4) for f in features]
    together = rollout_many(model, features, steps=4)
    assert [r.features.name for r in together] == [f.name for f in features]
    scale = max(np.abs(r.points).max() for r in alone)
    for a, b in zip(alone, together):
        assert b.joint_states.shape == a.joint_states.shape and b.points.shape == a.points.shape
        np.testing.assert_allclose(b.points, a.points, atol=1e-4 * scale, rtol=0)
        np.testing.assert_allclose(b.beam_states, a.beam_states, atol=1e-4 * np.abs(a.beam_states).max(), rtol=0)
    moved = np.abs(alone[0].points[-1] - alone[0].points[0]).max()
    assert moved > 1e-2 * scale  # the designs do move: the comparison is not of designs at rest


def test_a_compiled_union_gives_each_design_its_compiled_answer_alone(features):
    """graph_inputs of a list: one trace for the union (its size and design count traced in), whose points, split
    per design by GraphSet.points_of, are each design's compiled points alone (to float32 rounding: 1e-4 of the largest
    coordinate, as rollout_many's; over 30 initial weights the largest gap was 5e-5, 3e-5 with GNBlock.received;
    crosstalk would be ~1e-2); a union of another count is traced apart."""
    model = fitted(features, MODELS["local stiffness"])
    compiled = compile_rollout(model, features[0])
    batch = GraphSet.first_frames(features)
    with torch.no_grad():
        points = compiled(*graph_inputs(features))[2]
        tol = 1e-4 * points.abs().max().item()
        for i, f in enumerate(features):
            torch.testing.assert_close(batch.points_of(points, i), compiled(*graph_inputs(f))[2], atol=tol, rtol=0)
        two = compiled(*graph_inputs(features[:2]))[2]
        torch.testing.assert_close(GraphSet.first_frames(features[:2]).points_of(two, 1), batch.points_of(points, 1),
                                   atol=tol, rtol=0)
        one = compiled(*graph_inputs(features[:1]))[2]  # a list of one design: a union of one
        torch.testing.assert_close(one, compiled(*graph_inputs(features[0]))[2], atol=tol, rtol=0)
    assert len(compiled.traces) == 3 + len({(f.incidence.n_joints, f.incidence.n_beams) for f in features})


def test_an_ensemble_rolled_out_together_keeps_each_members_answer_per_design(features):
    members = [fitted(features, MODELS["additive"], seed=s) for s in (0, 1)]
    ensemble = Ensemble(members)
    together = rollout_many(ensemble, features[:2], steps=3)
    for f, r in zip(features[:2], together):
        alone = rollout(ensemble, f, steps=3)
        assert r.member_points.shape == alone.member_points.shape == (2, *alone.points.shape)
        np.testing.assert_allclose(r.member_points, alone.member_points, atol=1e-3, rtol=0)
        np.testing.assert_allclose(r.points, alone.member_points.mean(0), atol=1e-3, rtol=0)


def test_designs_whose_frame_times_differ_are_refused_unless_times_are_given(features):
    model = fitted(features, MODELS["additive"])
    late = replace(features[1], t=features[1].t ** 2)
    with pytest.raises(ValueError, match="frame times differ"):
        rollout_many(model, [features[0], late], steps=4)
    given = rollout_many(model, [features[0], late], steps=4, t=features[0].t)
    np.testing.assert_array_equal(given[1].t, features[0].t)
    with pytest.raises(ValueError, match="at least one design"):
        rollout_many(model, [], steps=4)
