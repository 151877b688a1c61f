"""learn.publish: a trained model kept in the repository (models/<name>/) answers as its runs did, and a changed
file is refused (tiny synthetic data; the committed models are checked against their cards)."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from data_schema.testing import synthetic_episode
from learn import checkpoint, ensemble, publish
from learn.evaluate import evaluate
from learn.rollout import rollout
from learn.train import train
from tests.test_learn_train import cfg_for, data_dir, tiny  # noqa: F401  (data_dir: the module fixture)

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parents[1]
COMMITTED = sorted(p.parent for p in (REPO / "models").glob(f"*/{publish.CARD}"))


@pytest.fixture(scope="module")
def members(data_dir, tmp_path_factory):  # noqa: F811
    a, b = tmp_path_factory.mktemp("pub_a"), tmp_path_factory.mktemp("pub_b")
    train(cfg_for("train", tiny(data_dir, a, "epochs=2", "optim.lr=3e-3")))
    train(cfg_for("train", tiny(data_dir, b, "epochs=2", "optim.lr=3e-3", "seed=5", f"split_from={a / 'last.pt'}")))
    return str(a / "last.pt"), str(b / "last.pt")


@pytest.fixture(scope="module")
def pair_report(members, tmp_path_factory):
    """The pair published once, then evaluated through its directory (one evaluation serves every test)."""
    root = tmp_path_factory.mktemp("pub")
    target = publish.publish(list(members), "pair_test", root / "models")
    evaluate(cfg_for("evaluate", ["timing_repeats=1", "plots=false", "split=val+test", f"checkpoint={target}",
                                  f"out_dir={root / 'report'}", "compiled_departures=1"]))  # two-epoch members
    # amplify round-off (tests/test_learn_train.py, the extra-dirs test): compiled vs eager is not this test's subject
    return target, root / "report"


def test_a_published_pair_answers_as_its_runs_and_its_card_holds_the_hashes(members, pair_report):
    target, _ = pair_report
    card = json.loads((target / publish.CARD).read_text())
    assert [m["file"] for m in card["members"]] == ["member_0.pt", "member_1.pt"] and card["report"] is None
    for m, src in zip(card["members"], members):
        f = target / m["file"]
        assert m["sha256"] == publish.sha256(f) and m["bytes"] == f.stat().st_size and m["source"] == src
        kept = torch.load(f, weights_only=True)  # still a plain-tensor checkpoint
        assert "optimizer" in checkpoint.load(src) and not set(publish.RESUME_ONLY) & set(kept)
        assert kept["split"] == checkpoint.load(src)["split"] and m["training"]["seed"] in (0, 5)
        assert f.stat().st_size < Path(src).stat().st_size  # the optimiser's moments left behind
    paths = ensemble.checkpoint_paths(str(target))  # the directory stands for its members, in order
    assert paths == [str(target / "member_0.pt"), str(target / "member_1.pt")]
    published, _ = ensemble.load(paths)
    original, _ = ensemble.load(list(members))
    assert card["n_parameters"] == published.n_parameters == original.n_parameters
    ep = synthetic_episode(3, 3, 5, 3, 3, frames=11, seed=9)
    assert np.array_equal(rollout(published, ep, steps=10).joint_states, rollout(original, ep, steps=10).joint_states)


def test_the_card_carries_the_figures_of_the_report_measured_with_exactly_its_members(pair_report, tmp_path):
    target, report_dir = pair_report
    on_disk = json.loads((report_dir / "report.json").read_text())
    paths = ensemble.checkpoint_paths(str(target))
    assert on_disk["checkpoint"] == paths  # an evaluation of models/<name> names the files it was measured with
    again = publish.publish(paths, "pair_with_report", tmp_path, report=report_dir)
    card = json.loads((again / publish.CARD).read_text())
    assert card["report"]["max_rel_error"]["p95"] == on_disk["max_rel_error"]["p95"]
    assert card["report"]["max_rel_error"]["per_family"] == on_disk["max_rel_error"]["per_family"]
    assert card["report"]["shape_rel_error"]["median"] == on_disk["shape_rel_error"]["median"]  # the shape apart from the tilt
    assert card["report"]["n_designs"] == on_disk["n_designs"] and card["report"]["speedup"] == on_disk["speedup"]
    assert [m["sha256"] for m in card["members"]] == [publish.sha256(p) for p in paths]  # byte for byte the same
    kept = json.loads((again / card["report"]["file"]).read_text())  # the whole report, for learn.compare later
    assert [d["name"] for d in kept["designs"]] == [d["name"] for d in on_disk["designs"]]
    assert not (target / "report.json").exists()  # none named, none kept
    with pytest.raises(ValueError, match="measured with .* not with checkpoints"):
        publish.publish(paths[:1], "only_one", tmp_path, report=report_dir)
    assert not (tmp_path / "only_one").exists()


def test_a_published_model_is_a_start_for_a_fine_tune_and_an_ensemble_is_refused_as_one(members, data_dir,  # noqa: F811
                                                                                          pair_report, tmp_path):
    target = publish.publish([members[0]], "start", tmp_path / "models")
    for i, start in enumerate([str(target), ensemble.checkpoint_paths(str(target))[0]]):  # the directory or its file
        train(cfg_for("train", tiny(data_dir, tmp_path / f"ft{i}", "epochs=1", f"init_from={start}")))
        tuned = checkpoint.load(tmp_path / f"ft{i}" / "last.pt")
        assert tuned["config"]["init_from"] == start and tuned["split"] == checkpoint.load(members[0])["split"]
    pair, _ = pair_report
    for key in ("init_from", "split_from"):
        with pytest.raises(ValueError, match=f"{key}=.*pair_test: a published ensemble of 2 members"):
            train(cfg_for("train", tiny(data_dir, tmp_path / key, "epochs=1", f"{key}={pair}")))
        assert not (tmp_path / key / "last.pt").exists()


def test_a_member_changed_after_publishing_is_refused_by_name(members, tmp_path):
    target = publish.publish([members[0]], "one", tmp_path)
    f = target / "member_0.pt"
    ckpt = torch.load(f, weights_only=True)
    ckpt["state_dict"] = {k: v + 1e-3 if v.is_floating_point() else v for k, v in ckpt["state_dict"].items()}
    torch.save(ckpt, f)
    with pytest.raises(ValueError, match=r"member_0.pt: sha256 .* differs"):
        ensemble.checkpoint_paths([str(target)])
    (target / "member_0.pt").unlink()
    with pytest.raises(FileNotFoundError, match="member_0.pt listed in card.json is missing"):
        ensemble.checkpoint_paths(str(target))
    (target / "card.json").unlink()  # a directory, but not a published model
    for read in (ensemble.checkpoint_paths, lambda p: publish.one_checkpoint(p, "init_from")):
        with pytest.raises(FileNotFoundError, match="one: not a published model .no card.json."):
            read(str(target))


@pytest.mark.parametrize("kwargs, error, message", [
    ({"name": "../escape"}, ValueError, "name='../escape': letters, digits"),
    ({"name": ".hidden"}, ValueError, "name='.hidden': letters, digits"),
    ({"name": "taken"}, FileExistsError, "name=taken: .* exists"),
    ({"name": "no_report", "report": "nowhere"}, FileNotFoundError, "does not exist"),
])
def test_bad_input_is_refused_by_name_and_writes_nothing(members, tmp_path, kwargs, error, message):
    (tmp_path / "taken").mkdir()
    if "report" in kwargs:
        kwargs = {**kwargs, "report": tmp_path / kwargs["report"]}
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(error, match=message):
        publish.publish(list(members), out_dir=tmp_path, **kwargs)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no directory, no temporary left behind


def test_overwrite_replaces_a_published_model_whole(members, tmp_path):
    publish.publish(list(members), "m", tmp_path)
    target = publish.publish([members[1]], "m", tmp_path, overwrite=True)
    assert sorted(p.name for p in target.iterdir()) == ["card.json", "member_0.pt"]
    assert json.loads((target / "card.json").read_text())["members"][0]["source"] == members[1]


@pytest.mark.parametrize("model_dir", COMMITTED, ids=[p.name for p in COMMITTED])
def test_every_committed_model_matches_its_card_and_loads(model_dir):
    paths = publish.members(model_dir)
    model, first = ensemble.load(paths)
    card = json.loads((model_dir / publish.CARD).read_text())
    assert model.n_parameters == card["n_parameters"] and {"val", "test"} <= set(first["split"])
