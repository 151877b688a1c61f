"""scripts/tail_anatomy.py: the tail's measures on a small fitted model and synthetic episodes."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from data_schema.testing import synthetic_episode
from learn.dataset import GraphSet
from learn.features import extract
from learn.model import Simulator
from learn.rollout import reference, rollout

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "scripts"))
import tail_anatomy  # noqa: E402


@pytest.fixture(scope="module")
def model_and_design():
    f = extract(synthetic_episode(3, 3, 5, 3, 3, frames=6, seed=4), name="ep4.h5")
    data = GraphSet.build([f])
    torch.manual_seed(0)
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16, 8], "pin_fixed_joint": True,
                           "update": "stiffness", "frame": "local"}, data.joint_state, data.beam_state,
                          data.static).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))  # a network that moves the design
    return model, f


def test_a_rollout_from_the_first_frame_is_the_answer_and_from_the_last_the_representation(model_and_design):
    model, f = model_and_design
    last = f.n_frames - 1
    with torch.inference_mode():
        got = tail_anatomy.anatomy(model, model, f, [0, last])
    assert got["from_frame"][0] == pytest.approx(got["error"], rel=1e-4)  # from frame 0: the rollout measured
    floor = np.linalg.norm(reference(f).local_points[-1] - f.fea_points[-1], axis=-1).max() / f.design_size
    assert got["from_frame"][1] == pytest.approx(floor, rel=1e-4, abs=1e-7)  # no step: the FEA frame as represented
    assert got["error"] > 10 * floor  # the perturbed network answers something else than the FEA
    assert 0.0 <= got["shape"] and np.isfinite(got["amplitude"]) and np.isfinite(got["hang"])
    P = rollout(model, f, steps=last, t=f.t).local_points
    joint = tail_anatomy.fixed_joint_points(f, P)
    np.testing.assert_allclose(joint[-1], joint[0], atol=1e-4)  # pinned: the answer's fixed joint stays


def test_designs_are_ranked_worst_first_from_both_parts_of_a_reference_evaluation(tmp_path):
    for part, names in (("52", {"episode_00001.h5": 0.02, "episode_00002.h5": 0.05}),
                        ("fresh", {"episode_100001.h5": 0.03})):
        (tmp_path / part).mkdir()
        designs = [{"name": n, "max_rel_error": e, "actuators": "mixed"} for n, e in names.items()]
        (tmp_path / part / "report.json").write_text(json.dumps({"designs": designs}))
    ranked = tail_anatomy.ranked_designs(tmp_path)
    assert [p.name for _, p, _ in ranked] == ["episode_00002.h5", "episode_100001.h5", "episode_00001.h5"]
    assert ranked[1][1].parent.name == "ds_heldout" and ranked[0][1].parent.name == "ds_default"
