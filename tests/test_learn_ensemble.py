"""learn.ensemble: several trainings answering as one, their spread as a validity signal (tiny synthetic data)."""
import json

import numpy as np
import pytest
import torch

from learn import checkpoint, ensemble
from learn.evaluate import evaluate
from learn.rollout import compile_rollout, graph_inputs, rollout
from learn.train import train
from learn.validity import check
from data_schema.testing import synthetic_episode
from tests.test_learn_train import cfg_for, data_dir, tiny  # noqa: F401  (data_dir: the module fixture)

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def members(data_dir, tmp_path_factory):  # noqa: F811
    """Two trainings on the same held-out designs, different seeds."""
    a, b = tmp_path_factory.mktemp("member_a"), tmp_path_factory.mktemp("member_b")
    train(cfg_for("train", tiny(data_dir, a, "epochs=3", "optim.lr=3e-3")))
    train(cfg_for("train", tiny(data_dir, b, "epochs=3", "optim.lr=3e-3", "seed=5", f"split_from={a / 'last.pt'}")))
    return a / "best.pt", b / "best.pt"


def test_the_answer_is_the_mean_of_the_members_answers_and_their_spread_is_reported(members):
    model, first = ensemble.load(list(members))
    assert isinstance(model, ensemble.Ensemble) and first["split"] == checkpoint.load(members[0])["split"]
    singles = [checkpoint.load_model(p) for p in members]
    assert model.n_parameters == sum(m.n_parameters for m in singles) and model.args["ensemble_members"] == 2
    assert "member_args" not in model.args  # same shape and settings: one set of args says it all
    model.members[1].answer_with(rollout_mirror=True)
    assert [a["rollout_mirror"] for a in model.args["member_args"]] == [False, True]
    model.members[1].answer_with(rollout_mirror=False)
    ep = synthetic_episode(3, 3, 5, 3, 3, frames=11, seed=9)
    r = rollout(model, ep, steps=10)
    parts = [rollout(m, ep, steps=10) for m in singles]
    assert np.allclose(r.joint_states, np.mean([p.joint_states for p in parts], axis=0), atol=1e-5)
    assert np.allclose(r.member_points, np.stack([p.points for p in parts]), atol=1e-4)
    verdict = check(model, r, max_dislocation_rel=1e9, range_margin=1e9)
    by_hand = np.linalg.norm(r.member_points - r.member_points.mean(0), axis=-1).max(axis=(0, 2))
    assert np.allclose(verdict.spread_per_frame, by_hand / ep_size(r)) and verdict.max_spread_rel > 0
    assert verdict.spread_per_frame[0] == pytest.approx(0.0, abs=1e-7)  # frame 0 is the design for every member
    strict = check(model, r, max_dislocation_rel=1e9, range_margin=1e9, max_spread_rel=verdict.max_spread_rel / 2)
    assert not strict.valid and "members disagree" in " ".join(strict.reasons)
    assert check(singles[0], parts[0], max_dislocation_rel=1e9, range_margin=1e9).max_spread_rel is None
    twins, _ = ensemble.load([members[0], members[0]])  # one network twice: no disagreement
    assert check(twins, rollout(twins, ep, steps=10), max_dislocation_rel=1e9, range_margin=1e9).max_spread_rel == 0


def ep_size(r) -> float:
    return r.features.design_size


def test_the_compiled_ensemble_rollout_gives_the_eager_numbers(members, data_dir):  # noqa: F811
    model, ckpt = ensemble.load(list(members))
    model.answer_with(rollout_mirror=True)  # every member with its mirror copy
    from learn.dataset import load_features
    f = load_features([data_dir / ckpt["split"]["test"][0]])[0]
    with torch.inference_mode():
        compiled = compile_rollout(model, f)(*graph_inputs(f))[0].numpy()
    assert np.allclose(compiled, rollout(model, f, steps=10).joint_states, atol=1e-4)


def test_evaluate_an_ensemble_reports_its_spread_and_refuses_members_with_other_held_out_designs(
        members, data_dir, tmp_path):  # noqa: F811
    base = ["timing_repeats=1", "plots=false", "split=val+test"]
    report = evaluate(cfg_for("evaluate", base + [f"checkpoint=[{members[0]},{members[1]}]", f"out_dir={tmp_path}"]))
    on_disk = json.loads((tmp_path / "report.json").read_text())
    assert on_disk["checkpoint"] == [str(p) for p in members] and on_disk["model"]["ensemble_members"] == 2
    assert on_disk["spread_rel"]["n"] == report["n_designs"] and "spread_error_spearman" in on_disk
    assert all(d["spread_rel"] > 0 for d in on_disk["designs"])
    assert "members' spread" in (tmp_path / "report.md").read_text()
    single = evaluate(cfg_for("evaluate", base + [f"checkpoint=[{members[0]}]", f"out_dir={tmp_path / 'one'}"]))
    assert "spread_rel" not in single and single["checkpoint"] == str(members[0])
    other = tmp_path / "other"  # same data, its own split (another seed): its held-out designs differ
    train(cfg_for("train", tiny(data_dir, other, "epochs=1", "seed=3")))
    if checkpoint.load(other / "last.pt")["split"]["val"] == checkpoint.load(members[0])["split"]["val"]:
        pytest.skip("seed 3 drew the same split on these 4 episodes")
    with pytest.raises(ValueError, match="ensemble member .* designs differ"):
        evaluate(cfg_for("evaluate", base + [f"checkpoint=[{members[0]},{other / 'last.pt'}]",
                                             f"out_dir={tmp_path / 'bad'}"]))
    assert not (tmp_path / "bad" / "report.json").exists()


def test_predict_with_an_ensemble_writes_its_spread_into_the_verdict(members, data_dir, tmp_path):  # noqa: F811
    from learn.predict import predict
    name = checkpoint.load(members[0])["split"]["test"][0]
    result = predict(cfg_for("predict", [f"checkpoint=[{members[0]},{members[1]}]", f"episode={data_dir / name}",
                                         f"out_dir={tmp_path}", "plots=false"]))
    on_disk = json.loads((tmp_path / "prediction.json").read_text())
    assert on_disk["checkpoint"] == [str(p) for p in members] and result["validity"]["max_spread_rel"] > 0
    assert len(on_disk["validity"]["spread_per_frame"]) == 11 and "max_rel_error" in on_disk


def test_bench_rollout_times_an_ensemble_with_every_members_copies(members, data_dir, tmp_path):  # noqa: F811
    import subprocess
    import sys
    from pathlib import Path
    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_rollout.py"
    r = subprocess.run([sys.executable, str(script), "--checkpoint", f"{members[0]},{members[1]}", "--data-dir",
                        str(data_dir), "--designs", "1", "--repeats", "1", "--settings", "1:true",
                        "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    header, row = (tmp_path / "rollout.csv").read_text().splitlines()
    assert header.startswith("backend,members,rotations,mirror,lattice_turns,copies")
    assert row.startswith("torchscript,2,1,True,1,4,")


@pytest.mark.parametrize("value", ["", [], ["a.pt", ""]])
def test_an_empty_checkpoint_value_is_refused_naming_the_key(value):
    with pytest.raises(ValueError, match="checkpoint=.*give one checkpoint path or a list"):
        ensemble.checkpoint_paths(value)
