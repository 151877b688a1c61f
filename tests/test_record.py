"""scripts/record.py: the record chain (conf/record.yaml) composes, waits for its data, runs its stages in order,
skips what is finished and never starts a stage from an unfinished one (tiny synthetic data)."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from data_schema.episode import write_episode
from data_schema.testing import synthetic_episode
from tests.test_learn_train import cfg_for

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
import record  # noqa: E402


def test_every_stage_of_the_record_composes_with_the_training_conf():
    cfg = record.conf()
    names = [s.name for s in cfg.stages]
    assert len(names) == len(set(names)) and cfg.stages[0]["from"] is None
    for stage in cfg.stages[1:]:  # each starts from an earlier stage's checkpoint
        assert stage["from"].split("/")[0] in names[:names.index(stage.name)]
    for stage in cfg.stages:
        train = cfg_for("train", list(stage.args))
        assert train.model.passes == 2 and train.threads == 1
    assert cfg_for("train", list(cfg.stages[0].args)).epochs == 18
    outs = {e.out for e in cfg.data}
    for stage in cfg.stages[1:]:  # the fine-tunes read only data the record generates
        train = cfg_for("train", list(stage.args))
        assert {train.data_dir, *train.train_extra_dirs, *train.val_extra_dirs} <= outs and train.init_required


def write_manifest(out: Path, episodes: dict[int, str]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "manifest.jsonl", "w") as f:
        for i, status in episodes.items():
            f.write(json.dumps({"episode": i, "status": status}) + "\n")


def test_missing_episodes_are_those_neither_written_nor_refused(tmp_path):
    write_manifest(tmp_path / "d", {10: "ok", 11: "contact", 12: "error", 13: "diverged", 16: "skipped"})
    entry = OmegaConf.create({"out": str(tmp_path / "d"), "start": 10, "n": 7, "args": []})
    # an error is retried by the generator: still missing; skipped: a whole file a killed generator left, kept
    assert record.missing_episodes(entry) == [12, 14, 15]


@pytest.fixture
def chain(tmp_path):
    data = tmp_path / "eps"
    for s in range(4):
        write_episode(data / f"ep{s:03d}.h5", synthetic_episode(3, 3, 5, 3, 3, frames=11, seed=s))
    write_manifest(data, {s: "ok" for s in range(4)})
    tiny = [f"data_dir={data}", "model.latent=16", "model.widths=[32,16]", "rotations=2", "lattice_turns=1",
            "log_every=100", "threads=1", "split.train=0.5", "split.val=0.25", "split.test=0.25", "epochs=1"]
    cfg = {"data": [{"out": str(data), "start": 0, "n": 4, "args": []}],
           "stages": [{"name": "a", "from": None, "args": tiny},
                      {"name": "b", "from": "a/last.pt", "args": [*tiny, "optim.lr=1e-4", "init_required=true"]}],
           "run_root": str(tmp_path / "runs" / "rec"), "seeds": [0, 1], "publish_as": "x"}
    path = tmp_path / "record.yaml"
    OmegaConf.save(OmegaConf.create(cfg), path)
    return path, tmp_path / "runs"


def test_the_stages_run_in_order_each_from_the_last_and_a_second_run_skips_them(chain, capsys):
    path, runs = chain
    assert record.main(["train", "--seed", "1", "--conf", str(path), "--budget-min", "30"]) == 0
    a, b = (torch.load(runs / "rec_s1" / n / "last.pt", weights_only=True) for n in ("a", "b"))
    assert a["finished"] and b["finished"] and a["config"]["seed"] == b["config"]["seed"] == 1
    assert b["config"]["init_from"] == str(runs / "rec_s1" / "a" / "last.pt")
    assert b["split"] == a["split"]
    capsys.readouterr()
    assert record.main(["train", "--seed", "1", "--conf", str(path)]) == 0
    out = capsys.readouterr().out
    assert "a: finished" in out and "b: finished" in out and "learn.train" not in out
    assert record.main(["members", "--conf", str(path)]) == 0
    assert capsys.readouterr().out.strip() == f"{runs}/rec_s0/b/last.pt,{runs}/rec_s1/b/last.pt"


def test_no_stage_starts_without_its_data_or_its_budget_nor_from_an_unfinished_one(chain, capsys):
    path, runs = chain
    cfg = OmegaConf.load(path)
    cfg.data[0].n = 6  # two episodes not generated yet
    short = path.with_name("short.yaml")
    OmegaConf.save(cfg, short)
    assert record.main(["train", "--seed", "0", "--conf", str(short)]) == record.WAITS and not runs.exists()
    assert "lacks 2 episodes; run make record-data" in capsys.readouterr().err
    assert record.main(["train", "--seed", "0", "--conf", str(path), "--budget-min", "0.01"]) == 3 and not runs.exists()
    paused = runs / "rec_s0" / "a"  # a first stage stopped by its time limit
    assert record.main(["train", "--seed", "0", "--conf", str(path), "--budget-min", "30"]) == 0
    ckpt = torch.load(paused / "last.pt", weights_only=True)
    torch.save({**ckpt, "finished": False}, paused / "last.pt")
    assert record.stage_state(paused)[0] == "paused"
    capsys.readouterr()
    assert record.main(["status", "--conf", str(path)]) == 0
    out = capsys.readouterr().out
    assert "a paused (epoch 1 of 1, " in out  # epochs done of the run's epochs
    assert "stage a: its data are complete" in out and "stage b: its data are complete" in out  # a is not done
    assert record.main(["train", "--seed", "0", "--conf", str(path), "--budget-min", "0.01"]) == 3  # resumes nothing, starts nothing
    assert "budget spent before a" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        record.main(["train", "--seed", "7", "--conf", str(path)])


def test_without_a_seed_every_seed_trains_side_by_side_each_into_its_own_log(chain, tmp_path, capsys):
    path, runs = chain
    assert record.main(["train", "--conf", str(path), "--log-dir", str(tmp_path / "logs")]) == 0
    out = capsys.readouterr().out
    for seed in (0, 1):
        assert torch.load(runs / f"rec_s{seed}" / "b" / "last.pt", weights_only=True)["finished"]
        assert f"seed {seed}: every stage finished" in out
        assert "every stage finished" in (tmp_path / "logs" / f"rec_s{seed}.log").read_text()  # run_root's name


def test_a_stage_waits_only_for_the_data_it_needs(chain, capsys):
    path, runs = chain
    cfg = OmegaConf.load(path)
    cfg.data[0].n = 6  # two episodes past the four the first stage reads are not generated yet
    cfg.stages[0].needs = {cfg.data[0].out: 4}
    partial = path.with_name("partial.yaml")
    OmegaConf.save(cfg, partial)
    assert record.main(["train", "--seed", "0", "--conf", str(partial), "--budget-min", "30"]) == record.WAITS
    assert torch.load(runs / "rec_s0" / "a" / "last.pt", weights_only=True)["finished"]  # a ran, b waits
    assert not (runs / "rec_s0" / "b").exists()
    assert "b: its data are not complete" in capsys.readouterr().err
    log_dir = path.parent / "logs"  # side by side: waiting for data is an outcome, not a failure
    assert record.main(["train", "--conf", str(partial), "--log-dir", str(log_dir)]) == record.WAITS
    assert capsys.readouterr().out.count("waits for data: make record-data") == 2
    assert "lacks 2 episodes" in (log_dir / "rec_s1.log").read_text()
    assert record.main(["status", "--conf", str(partial)]) == 0
    out = capsys.readouterr().out
    assert "stage a: done by every seed" in out and "stage b: waits for" in out and "2 missing of its first 6" in out
    for bad in ({"elsewhere": 2}, {cfg.data[0].out: 7}, {cfg.data[0].out: 0}):
        cfg.stages[0].needs = bad
        OmegaConf.save(cfg, partial)
        with pytest.raises(ValueError, match="stage a: needs"):
            record.main(["train", "--seed", "0", "--conf", str(partial)])


def test_with_wait_a_stage_starts_once_the_generator_completes_its_data_and_gives_up_with_the_budget(
        chain, capsys, monkeypatch):
    path, runs = chain
    cfg = OmegaConf.load(path)
    cfg.data[0].n = 6  # two episodes the generator beside has not written yet
    short = path.with_name("short.yaml")
    OmegaConf.save(cfg, short)
    data = Path(cfg.data[0].out)
    looks = []

    def generator_finishes(seconds):  # each poll's sleep: the second one finds the solver's last two refusals
        looks.append(seconds)
        if len(looks) == 2:
            with open(data / "manifest.jsonl", "a") as f:
                f.writelines(json.dumps({"episode": i, "status": "contact"}) + "\n" for i in (4, 5))

    monkeypatch.setattr(record.time, "sleep", generator_finishes)
    assert record.main(["train", "--seed", "0", "--conf", str(short), "--budget-min", "0.01", "--wait"]) == \
        record.WAITS and not looks and not runs.exists()  # no stage's minimum left: no wait, no stage
    capsys.readouterr()
    assert record.main(["train", "--seed", "0", "--conf", str(short), "--budget-min", "30", "--wait"]) == 0
    assert looks == [record.POLL_S] * 2
    assert torch.load(runs / "rec_s0" / "b" / "last.pt", weights_only=True)["finished"]
    out = capsys.readouterr().out
    assert "a: waiting for its data" in out and "lacks 2 episodes" in out


def test_the_record_reference_stage_needs_only_the_episodes_its_training_designs_come_from():
    cfg = record.conf()
    ref = cfg.stages[0]
    train = cfg_for("train", list(ref.args))
    assert dict(ref.needs) == {train.data_dir: 400} and train.train_designs == 348
    held = OmegaConf.load(REPO / train.split_from)  # its 52 held-out designs are among the 400 too
    assert len(held.val) + len(held.test) == 400 - 348
    assert all(int(n.split("_")[1].split(".")[0]) < 400 for n in [*held.val, *held.test])


def test_a_kept_stage_is_published_when_it_finishes_and_the_next_starts_from_it_once_the_run_is_gone(chain, capsys):
    import shutil

    path, runs = chain
    cfg = OmegaConf.load(path)
    cfg.stages[0].keep = "last.pt"
    cfg.keep_dir = str(runs.parent / "models")
    kept_conf = path.with_name("kept.yaml")
    OmegaConf.save(cfg, kept_conf)
    assert record.main(["train", "--seed", "0", "--conf", str(kept_conf), "--budget-min", "30"]) == 0
    kept = runs.parent / "models" / "rec_s0_a"
    card = json.loads((kept / "card.json").read_text())
    assert card["members"][0]["source"] == str(runs / "rec_s0" / "a" / "last.pt") and "optimizer" not in torch.load(
        kept / "member_0.pt", weights_only=True)
    assert not (runs.parent / "models" / "rec_s0_b").exists()  # b has no keep
    assert "kept as" in capsys.readouterr().out
    shutil.rmtree(runs)  # a fresh machine: the runs are gone, the committed directory is not
    assert record.main(["status", "--conf", str(kept_conf)]) == 0
    out = capsys.readouterr().out
    assert "a kept" in out and "b new" in out
    ran = torch.load(kept / "member_0.pt", weights_only=True)["history"]  # a's epoch length survives in its member
    assert record.epoch_minutes(cfg, 0, cfg.stages[0]) == pytest.approx(ran[-1]["seconds"] / 60)
    assert record.main(["train", "--seed", "0", "--conf", str(kept_conf), "--budget-min", "30"]) == 0
    b = torch.load(runs / "rec_s0" / "b" / "last.pt", weights_only=True)
    assert b["finished"] and b["config"]["init_from"] == str(kept) and not (runs / "rec_s0" / "a").exists()
    cfg.stages[0].keep = "best.pt"  # b starts from a/last.pt: keeping another file would not carry it on
    OmegaConf.save(cfg, kept_conf)
    with pytest.raises(ValueError, match="keep the file the next stage starts from"):
        record.main(["train", "--seed", "0", "--conf", str(kept_conf)])


def test_no_stage_starts_on_less_budget_than_one_epoch_of_it(chain, capsys):
    path, runs = chain  # learn.train trains one epoch before it looks at its limit: less would overrun the budget
    cfg = OmegaConf.load(path)
    cfg.stages.append({"name": "c", "from": "b/last.pt", "args": list(cfg.stages[1].args)})  # b's recipe again
    three = path.with_name("three.yaml")
    OmegaConf.save(cfg, three)
    assert record.main(["train", "--seed", "0", "--conf", str(path), "--budget-min", "30"]) == 0  # a and b
    b = runs / "rec_s0" / "b" / "last.pt"
    ckpt = torch.load(b, weights_only=True)
    ckpt["history"][-1]["seconds"] = 1800.0  # b's one epoch as long as a fine-tune's epoch on 1,045 designs
    torch.save(ckpt, b)
    cfg = record.conf(three)
    assert record.epoch_minutes(cfg, 0, cfg.stages[2]) == pytest.approx(30.0)  # c: b's, the same args
    data = Path(cfg.data[0].out)  # two more episodes since b: c trains on 2 + 2 designs where b had 2
    for s in (4, 5):
        write_episode(data / f"ep{s:03d}.h5", synthetic_episode(3, 3, 5, 3, 3, frames=11, seed=s))
    assert len(ckpt["split"]["train"]) == 2 and record.epoch_minutes(cfg, 0, cfg.stages[2]) == pytest.approx(60.0)
    for s in (4, 5):
        (data / f"ep{s:03d}.h5").unlink()
    grown = record.conf(three)  # a fresh machine: its data entry grown by two episodes, not yet generated
    grown.data[0].n = 6
    assert record.epoch_minutes(grown, 0, grown.stages[2]) == pytest.approx(60.0)  # counted as they will be
    assert 0 < record.epoch_minutes(cfg, 0, cfg.stages[0]) < 1  # a: its own run's
    assert record.epoch_minutes(cfg, 1, cfg.stages[2]) is None  # seed 1 has trained nothing
    assert record.minimum_minutes(cfg, 1, cfg.stages[2]) == record.MIN_STAGE_MIN
    capsys.readouterr()
    assert record.main(["status", "--conf", str(three)]) == 0  # what the next stage costs, for planning a session
    out = capsys.readouterr().out
    assert "seed 0 next: c, ~30 min an epoch x 1 epochs left = ~30 min (a budget under 33 min" in out
    assert record.main(["train", "--seed", "0", "--conf", str(three), "--budget-min", "20"]) == 3
    assert not (runs / "rec_s0" / "c").exists()
    assert "budget spent before c (20 min left, 33 needed: one epoch of it)" in capsys.readouterr().out
    assert record.main(["train", "--seed", "0", "--conf", str(three), "--budget-min", "40"]) == 0
    assert torch.load(runs / "rec_s0" / "c" / "last.pt", weights_only=True)["finished"]


def test_runs_of_consecutive_indices():
    assert record.runs_of([]) == [] and record.runs_of([3, 4, 5, 9, 11, 12]) == [(3, 3), (9, 1), (11, 2)]


def test_packed_episodes_are_not_solved_again_on_a_fresh_machine(tmp_path, monkeypatch, capsys):
    """record pack: solved episodes and refusals -> parts of pack_part; a fresh machine (no data/) gets them in place,
    counts them done, lists and reads them; record data solves only what no pack holds; a later pack adds a part."""
    from learn.dataset import episode_paths, load_features

    out = tmp_path / "data" / "ds"
    for i in (0, 1, 3):
        write_episode(record.episode_path(out, i), synthetic_episode(2, 2, 5, 3, 3, frames=3, seed=i))
    write_manifest(out, {0: "ok", 1: "ok", 2: "contact", 3: "ok", 4: "error"})
    cfg = {"data": [{"out": str(out), "start": 0, "n": 6, "args": []}], "stages": [], "seeds": [0],
           "run_root": str(tmp_path / "runs"), "publish_as": "x", "pack_dir": str(tmp_path / "packs"), "pack_part": 2}
    path = tmp_path / "record.yaml"
    OmegaConf.save(OmegaConf.create(cfg), path)
    before = {f.name: f for f in load_features(episode_paths(out))}
    assert record.main(["pack", "--conf", str(path)]) == 0
    parts = sorted(p.name for p in (tmp_path / "packs" / "ds").glob("*.h5"))
    assert parts == ["part_00000-00001.h5", "part_00002-00003.h5"]  # the error (4) is not packed: it is retried

    import shutil
    shutil.rmtree(tmp_path / "data")  # a fresh machine: the repository's packs only
    calls = []
    monkeypatch.setattr(record.subprocess, "call", lambda cmd, cwd=None: calls.append(cmd) or 0)
    assert record.main(["data", "--conf", str(path)]) == 0
    assert [c[3:5] for c in calls] == [["n=2", "start=4"]]  # only 4 (an error) and 5 (never tried)
    assert record.missing_episodes(OmegaConf.create(cfg).data[0]) == [4, 5]
    after = load_features(episode_paths(out))
    assert [f.name for f in after] == sorted(before)
    for f in after:
        assert np.array_equal(f.beam_state, before[f.name].beam_state) and f.fea_seconds == before[f.name].fea_seconds
    capsys.readouterr()
    assert record.main(["status", "--conf", str(path)]) == 0
    assert f"4 of 6 episodes done (4 of them in the repository's feature packs, {tmp_path}/packs/ds)" in capsys.readouterr().out

    write_episode(record.episode_path(out, 5), synthetic_episode(2, 2, 5, 3, 3, frames=3, seed=5))
    with open(out / "manifest.jsonl", "a") as f:
        f.write(json.dumps({"episode": 5, "status": "ok"}) + "\n")
    assert record.main(["pack", "--conf", str(path)]) == 0  # only the new episode: a new part, old parts untouched
    assert sorted(p.name for p in (tmp_path / "packs" / "ds").glob("*.h5")) == [*parts, "part_00005-00005.h5"]
    assert record.missing_episodes(OmegaConf.create(cfg).data[0]) == [4]


def test_record_data_packs_each_batch_as_soon_as_it_is_solved(tmp_path, monkeypatch):
    """pack_part 2 over 5 new episodes: the generator is asked for [0, 2), [2, 4), [4, 5) and each batch is packed
    before the next starts; a generator that fails mid-batch leaves what it solved packed and the exit code."""
    out = tmp_path / "data" / "ds"
    cfg = {"data": [{"out": str(out), "start": 0, "n": 5, "args": []}], "stages": [], "seeds": [0],
           "run_root": str(tmp_path / "runs"), "publish_as": "x", "pack_dir": str(tmp_path / "packs"), "pack_part": 2}
    path = tmp_path / "record.yaml"
    OmegaConf.save(OmegaConf.create(cfg), path)
    seen = []

    def generator(cmd, cwd=None):  # solves its range (synthetic episodes), the last one failing on request
        n, start = (int(a.split("=")[1]) for a in cmd[3:5])
        seen.append((start, n, sorted(p.name for p in (tmp_path / "packs" / "ds").glob("*.h5"))))
        for i in range(start, start + n):
            if i == fail_at:
                return 1
            write_episode(record.episode_path(out, i), synthetic_episode(2, 2, 5, 3, 3, frames=3, seed=i))
            with open(out / "manifest.jsonl", "a") as f:
                f.write(json.dumps({"episode": i, "status": "ok"}) + "\n")
        return 0

    monkeypatch.setattr(record.subprocess, "call", generator)
    fail_at = 3
    assert record.main(["data", "--conf", str(path)]) == 1
    assert seen == [(0, 2, []), (2, 2, ["part_00000-00001.h5"])]
    assert sorted(p.name for p in (tmp_path / "packs" / "ds").glob("*.h5")) == ["part_00000-00001.h5",
                                                                                "part_00002-00002.h5"]
    fail_at, seen[:] = None, []
    assert record.main(["data", "--conf", str(path)]) == 0
    assert [s[:2] for s in seen] == [(3, 2)]
    assert sorted(p.name for p in (tmp_path / "packs" / "ds").glob("*.h5"))[-1] == "part_00003-00004.h5"


def test_a_paused_stage_parked_in_the_repository_resumes_on_a_fresh_machine(chain, capsys):
    import shutil

    path, runs = chain
    cfg = OmegaConf.load(path)
    cfg.park_dir = str(runs.parent / "models" / "paused")
    cfg.stages = [cfg.stages[0]]
    parked_conf = path.with_name("parked.yaml")
    OmegaConf.save(cfg, parked_conf)
    assert record.main(["train", "--seed", "0", "--conf", str(parked_conf), "--budget-min", "30"]) == 0
    last = runs / "rec_s0" / "a" / "last.pt"
    ckpt = torch.load(last, weights_only=True)
    ckpt = {**ckpt, "finished": False, "config": {**ckpt["config"], "epochs": 2}}
    torch.save(ckpt, last)  # a paused after the first of two epochs, as a time limit leaves it
    cfg.stages[0].args = [*cfg.stages[0].args, "epochs=2"]
    OmegaConf.save(cfg, parked_conf)
    assert record.main(["park", "--conf", str(parked_conf)]) == 0
    parked = runs.parent / "models" / "paused" / "rec_s0_a.pt"
    assert parked.read_bytes() == last.read_bytes() and "parked as" in capsys.readouterr().out
    assert not (runs.parent / "models" / "paused" / "rec_s1_a.pt").exists()  # seed 1 never started: nothing parked
    shutil.rmtree(runs)  # a fresh machine: the run is gone, the committed parked file is not
    assert record.main(["status", "--conf", str(parked_conf)]) == 0
    out = capsys.readouterr().out
    assert "put back as its run's last.pt" in out and "a paused (epoch 1 of 2, " in out
    assert record.main(["train", "--seed", "0", "--conf", str(parked_conf), "--budget-min", "30"]) == 0
    resumed = torch.load(last, weights_only=True)
    assert resumed["finished"] and len(resumed["history"]) == 2  # one more epoch, not the stage again
    assert resumed["history"][0] == ckpt["history"][0] and resumed["split"] == ckpt["split"]
    capsys.readouterr()
    assert record.main(["park", "--conf", str(parked_conf)]) == 0  # finished now: its parked file goes
    assert not parked.exists() and "parked checkpoint deleted" in capsys.readouterr().out
    assert record.main(["status", "--conf", str(parked_conf)]) == 0 and "a finished" in capsys.readouterr().out
    del cfg["park_dir"]
    OmegaConf.save(cfg, parked_conf)
    with pytest.raises(ValueError, match="needs park_dir"):
        record.main(["park", "--conf", str(parked_conf)])


def test_another_chain_of_the_same_stages_by_overrides_leaves_the_default_chain_alone(chain, capsys):
    """--set (make record RECORD_SET=...): stage_args reach every stage's learn.train, and the chain lives under its
    own run_root (runs, keeps and parks named after it); a key the conf does not have is refused by name."""
    path, runs = chain
    cfg = OmegaConf.load(path)
    cfg.stage_args = []
    OmegaConf.save(cfg, path)
    one = ["--set", f"run_root={runs / 'one'}", "--set", "stage_args=[model.passes=1]"]
    assert record.main(["train", "--seed", "0", "--conf", str(path), "--budget-min", "30", *one]) == 0
    for name in ("a", "b"):
        ckpt = torch.load(runs / "one_s0" / name / "last.pt", weights_only=True)
        assert ckpt["finished"] and ckpt["config"]["model"]["passes"] == 1
    assert not (runs / "rec_s0").exists()  # the default chain untouched
    capsys.readouterr()
    assert record.main(["members", "--conf", str(path), *one]) == 0
    assert capsys.readouterr().out.strip() == f"{runs}/one_s0/b/last.pt,{runs}/one_s1/b/last.pt"
    assert record.main(["publish-name", "--conf", str(path), "--set", "publish_as=one_pair"]) == 0
    assert capsys.readouterr().out.strip() == "one_pair"
    with pytest.raises(SystemExit):
        record.main(["status", "--conf", str(path), "--set", "run_rot=runs/x"])
    assert "--set 'run_rot=runs/x': must be <key>=<value> with a top-level key of record.yaml" in capsys.readouterr().err
