"""Dataset generation: resume after a kill, skip valid episodes, refuse bad config early, reproducible seeds."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx")

ROOT = Path(__file__).resolve().parent.parent
FAST = ["mesh=coarse", "progress=false"]


def generate(out: Path, *args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fea_factory.generate", f"out={out}", *FAST, *args],
                          stdin=subprocess.DEVNULL,
                          cwd=ROOT, capture_output=True, text=True, timeout=900, **kw)


def manifest(out: Path) -> list[dict]:
    p = out / "manifest.jsonl"
    return [json.loads(line) for line in p.read_text().splitlines()] if p.exists() else []


def test_generate_config_composes_with_every_launcher():
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="generate", overrides=["hydra/launcher=slurm"], return_hydra_config=True)
        assert cfg.hydra.launcher.timeout_min > 0
        assert "submitit" in cfg.hydra.launcher._target_
        cfg = compose(config_name="generate", overrides=["n=3", "mesh=fine"])
        assert cfg.mesh.nodes_length == 17 and cfg.n == 3


@pytest.mark.parametrize("override, field", [("mesh.nodes_length=4", "mesh.nodes_length"),
                                             ("jobs=0", "jobs"), ("solver.save_every=7", "solver.save_every"),
                                             ("material.poisson=0.5", "material.poisson"),
                                             ("scene.fixed_face=false", "fixed_face"),
                                             ("material.residual_stress.sigma=0.25", "material.residual_stress.sigma"),
                                             ("shard=3", "shard")])
def test_invalid_config_is_refused_before_any_solve(tmp_path, override, field):
    r = generate(tmp_path / "ds", "n=1", override)
    assert r.returncode == 2
    assert field in r.stderr
    assert not list((tmp_path / "ds").glob("*.h5")) and not manifest(tmp_path / "ds")


@pytest.mark.parametrize("override, message", [
    ("n=2.5", "n = 2.5: must be an integer >= 1 (episodes)"),  # int() read it as 2 before
    ("start=-1", "start = -1: must be an integer >= 0 (first episode index)"),  # made episode_-0001.h5
    ("seed=-3", "seed = -3: must be an integer >= 0 (design seed)"),  # numpy's SeedSequence error, per episode
    ("jobs=two", "jobs = 'two': must be an integer >= 1 (episodes solved at once)"),
    ("np=true", "np = True: must be an integer >= 1 (MPI ranks per episode)"),
    ("shard=0.5", "shard = 0.5: must be an integer >= 0 (this process's share)"),
    ("retry_refused=1", "retry_refused = 1: must be true or false")])
def test_a_count_that_is_not_an_integer_in_range_is_refused_by_name(override, message):
    from hydra import compose, initialize_config_dir

    from fea_factory.generate import GenerateConfigError, check_config

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="generate", overrides=[override])
    with pytest.raises(GenerateConfigError) as err:
        check_config(cfg)
    assert str(err.value) == message


def test_kill_mid_episode_then_resume_completes_the_set(tmp_path):
    from data_schema.validate import validate_episode

    out = tmp_path / "ds"
    proc = subprocess.Popen([sys.executable, "-m", "fea_factory.generate", f"out={out}", "n=2", *FAST],
                            cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    deadline = time.time() + 600
    while time.time() < deadline and len(manifest(out)) < 1:  # first episode done, second under way
        time.sleep(0.5)
    busy = generate(out, "n=2")  # a second generator on the same shard while the first lives: refused, nothing done
    assert busy.returncode == 3 and f"out={out} (shard 0 of 1) is in use by process {proc.pid}" in busy.stderr
    time.sleep(3.0)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert len(manifest(out)) == 1
    assert not (out / "episode_00001.h5").exists()  # nothing half-written under the final name
    lock = out / ".generate.shard0of1.lock"
    assert lock.read_text() == str(proc.pid)  # the killed generator's lock stays behind ...
    r = generate(out, "n=2")
    assert r.returncode == 0, r.stderr[-2000:]
    assert not lock.exists()  # ... and the next one takes it over, and lets it go when done
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["done"] == 1 and summary["skipped"] == 1
    # a valid file whose manifest line was lost (killed between rename and append) gets a "skipped" record
    lines = (out / "manifest.jsonl").read_text().splitlines()
    (out / "manifest.jsonl").write_text("\n".join(l for l in lines if json.loads(l)["episode"] != 0) + "\n")
    r = generate(out, "n=2")
    assert r.returncode == 0, r.stderr[-2000:]
    records = {rec["episode"]: rec for rec in manifest(out)}
    assert sorted(records) == [0, 1] and records[0]["status"] == "skipped" and records[0]["bytes"] > 0
    r = generate(out, "n=2")  # and only once
    assert len(manifest(out)) == 2
    files = sorted(out.glob("episode_*.h5"))
    assert [f.name for f in files] == ["episode_00000.h5", "episode_00001.h5"]
    assert all(validate_episode(f) == [] for f in files)
    assert not list(out.glob("*.tmp"))
    # the same seed regenerates episode 1 alone, identically
    again = tmp_path / "again"
    r = generate(again, "n=1", "start=1")
    assert r.returncode == 0, r.stderr[-2000:]
    from data_schema.episode import read_episode

    a, b = read_episode(out / "episode_00001.h5"), read_episode(again / "episode_00001.h5")
    assert a.design_json == b.design_json
    np.testing.assert_allclose(a.node_xyz, b.node_xyz, atol=1e-6)
    np.testing.assert_allclose(a.stress, b.stress, atol=1e-7)


def test_a_grid_that_comes_closer_than_min_clearance_is_refused_not_written(tmp_path):
    out = tmp_path / "ds"
    generate(out, "n=1", "grid=g2x2", "solver.min_clearance_mm=10000")  # every design is "too close"
    rec = manifest(out)[-1]
    assert rec["status"] == "contact" and "solver.min_clearance_mm = 10000" in rec["reason"]
    assert rec["clearance_mm"] > 0 and not list(out.glob("episode_*.h5"))
    # the same design under the same settings is not solved again: the refusal stands, no new record
    r = generate(out, "n=1", "grid=g2x2", "solver.min_clearance_mm=10000")
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout.strip().splitlines()[-1])["refused_before"] == 1
    assert "retry_refused=true" in r.stderr and len(manifest(out)) == 1
    generate(out, "n=1", "grid=g2x2", "solver.min_clearance_mm=10000", "retry_refused=true")  # asked: solved again
    assert [rec["status"] for rec in manifest(out)] == ["contact", "contact"]
    assert manifest(out)[0]["attempt"] == manifest(out)[1]["attempt"]
    generate(out, "n=1", "grid=g2x2")  # the default limit, a new attempt: written, its clearance recorded
    rec = manifest(out)[-1]
    assert rec["status"] == "ok" and rec["clearance_mm"] > 0.5
    from data_schema.episode import read_episode
    stats = json.loads(read_episode(out / "episode_00000.h5").solver_stats_json)
    assert stats["clearance_mm"] == rec["clearance_mm"]
    assert 0.0 <= stats["load_per_cpu"] < 100  # how busy the machine was: tells inflated wall times
