"""Prediction from a design with no FEA: fea_factory.initial is frame 0 of the solved episode; learn.predict rolls a
trained model out from it and writes a ParaView view that reads back as the rollout."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest

from data_schema.episode import read_episode, write_episode
from data_schema.testing import synthetic_episode
from learn import checkpoint
from learn.predict import predict
from learn.rollout import rollout
from learn.shapes import block_hexahedra, hex_volumes
from test_learn_train import cfg_for, data_dir, trained  # noqa: F401  (module fixtures: tiny episodes, a model)

ROOT = Path(__file__).resolve().parent.parent


def run(module: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", module, *args], stdin=subprocess.DEVNULL, cwd=ROOT,
                          capture_output=True, text=True, timeout=900)


def test_initial_episode_is_frame_0_of_the_solved_one(tmp_path):
    pytest.importorskip("dolfinx")
    out = tmp_path / "ds"
    r = run("fea_factory.generate", f"out={out}", "n=1", "grid=g2x2", "mesh=coarse", "progress=false")
    assert r.returncode == 0, r.stderr[-2000:]
    solved = read_episode(out / "episode_00000.h5")
    r = run("fea_factory.initial", f"design={out / 'designs' / 'episode_00000.json'}", f"out={tmp_path / 'i.h5'}",
            "mesh=coarse")
    assert r.returncode == 0, r.stderr[-2000:]
    initial = read_episode(tmp_path / "i.h5")
    assert initial.n_frames == 1 and initial.t.tolist() == [0.0] and len(initial.increment_t) == 0
    for field in ("node_xyz0", "cell_nodes", "cell_key", "joint_nodes", "beam_nodes", "joint_cells", "beam_cells",
                  "quad_points", "quad_weights", "beam_kind", "fixed_joint"):
        np.testing.assert_array_equal(getattr(initial, field), getattr(solved, field), err_msg=field)
    np.testing.assert_array_equal(initial.node_xyz[0], solved.node_xyz[0])
    np.testing.assert_array_equal(initial.stress[0], solved.stress[0])  # no stress before triggering
    bad = run("fea_factory.initial", f"design={out / 'designs' / 'episode_00000.json'}", f"out={tmp_path / 'b.h5'}",
              "mesh.nodes_length=4")
    assert bad.returncode == 2 and "nodes_length" in bad.stderr and not (tmp_path / "b.h5").exists()


def test_block_hexahedra_fill_the_flat_blocks():
    """Frame 0: each block's coarse hexahedra have exactly the volume of its fine mesh cells (flat blocks, planar
    faces); every cell positively oriented."""
    from learn.features import extract, rebuild_all_points

    ep = synthetic_episode(3, 3, 5, 3, 3, frames=3)
    f = extract(ep)
    pts = rebuild_all_points(f.joint_state[0].astype(float), f.beam_state[0].astype(float))
    cells, block = block_hexahedra(f.incidence.n_joints, f.incidence.n_beams)
    coarse = np.bincount(block, weights=hex_volumes(pts, cells))
    fine = np.bincount(ep.cell_key[:, 0], weights=hex_volumes(ep.node_xyz0.astype(float), ep.cell_nodes))
    assert (hex_volumes(pts, cells) > 0).all()
    np.testing.assert_allclose(coarse, fine, rtol=1e-5)  # features are float32: ~1e-7 mm on 4 mm thick blocks


def test_predict_writes_view_verdict_and_error_like_the_rollout(trained, data_dir, tmp_path):  # noqa: F811
    run_dir, _ = trained
    ckpt = checkpoint.load(run_dir / "best.pt")
    name = ckpt["split"]["test"][0]
    base = [f"checkpoint={run_dir / 'best.pt'}", "threads=1"]
    full = predict(cfg_for("predict", base + [f"episode={data_dir / name}", f"out_dir={tmp_path / 'full'}"]))
    raw = rollout(checkpoint.model_from(ckpt), read_episode(data_dir / name))
    want = raw.welded()  # the answer is one solid by default (conf/predict.yaml weld)
    err = np.linalg.norm(want.local_points - want.features.fea_points, axis=-1)
    assert full["welded"] and full["max_rel_error"] == pytest.approx(err.max() / want.features.design_size, rel=1e-5)
    blocks = predict(cfg_for("predict", base + [f"episode={data_dir / name}", f"out_dir={tmp_path / 'blocks'}",
                                                "weld=false", "plots=false"]))
    raw_err = np.linalg.norm(raw.local_points - raw.features.fea_points, axis=-1)
    assert blocks["max_rel_error"] == pytest.approx(raw_err.max() / raw.features.design_size, rel=1e-5)
    assert blocks["validity"] == full["validity"]  # checked on the blocks as predicted either way
    assert json.loads((tmp_path / "full" / "prediction.json").read_text())["valid"] == full["valid"]
    assert (tmp_path / "full" / "prediction.png").stat().st_size > 0
    reader = meshio.xdmf.TimeSeriesReader(tmp_path / "full" / "prediction.view.xdmf")
    points, _ = reader.read_points_cells()
    _, last, _ = reader.read_data(reader.num_steps - 1)
    np.testing.assert_allclose(points + last["displacement"], want.points[-1], atol=1e-4)
    np.testing.assert_allclose(last["error_mm"], err[-1], atol=1e-4)

    ep = read_episode(data_dir / name)  # the same design before triggering: frame 0 only, no reference
    one = ep.replace(t=ep.t[:1], node_xyz=ep.node_xyz[:1], stress=ep.stress[:1])
    write_episode(tmp_path / "initial.h5", one)
    alone = predict(cfg_for("predict", base + [f"episode={tmp_path / 'initial.h5'}", f"out_dir={tmp_path / 'one'}"]))
    assert "max_rel_error" not in alone and alone["t"] == pytest.approx(ep.t)
    reader = meshio.xdmf.TimeSeriesReader(tmp_path / "one" / "prediction.view.xdmf")
    reader.read_points_cells()
    _, last_alone, _ = reader.read_data(reader.num_steps - 1)
    assert "error_mm" not in last_alone
    np.testing.assert_allclose(last_alone["displacement"], last["displacement"], atol=1e-4)
    with pytest.raises(ValueError, match="steps=0"):
        predict(cfg_for("predict", base + [f"episode={tmp_path / 'initial.h5'}", "steps=0",
                                           f"out_dir={tmp_path / 'bad'}"]))


def test_predict_many_designs_in_one_pass_writes_each_as_alone(trained, data_dir, tmp_path):  # noqa: F811
    """episode=DIR or a list: every design rolled out together (rollout_many), each one's outputs in its own directory
    with the verdict and error it gets alone, and a table with a row per design."""
    run_dir, _ = trained
    names = sorted(p.name for p in data_dir.glob("*.h5"))[:2]
    for name in names:
        (tmp_path / "in").mkdir(exist_ok=True)
        (tmp_path / "in" / name).symlink_to(data_dir / name)
    base = [f"checkpoint={run_dir / 'best.pt'}", "threads=1", "plots=false"]
    many = predict(cfg_for("predict", base + [f"episode={tmp_path / 'in'}", f"out_dir={tmp_path / 'many'}"]))
    assert [Path(r["episode"]).name for r in many] == names and many[0]["batch"] == 2
    for name, result in zip(names, many):
        alone = predict(cfg_for("predict", base + [f"episode={data_dir / name}", f"out_dir={tmp_path / name}"]))
        assert result["max_rel_error"] == pytest.approx(alone["max_rel_error"], rel=1e-4)
        assert result["valid"] == alone["valid"]
        assert (tmp_path / "many" / Path(name).stem / "prediction.view.xdmf").is_file()
    rows = (tmp_path / "many" / "predictions.csv").read_text().splitlines()
    assert rows[0].startswith("episode,valid,max_rel_error") and len(rows) == 3
    listed = predict(cfg_for("predict", base + [f"episode=[{data_dir / names[1]}]", f"out_dir={tmp_path / 'l'}"]))
    assert len(listed) == 1 and listed[0]["max_rel_error"] == pytest.approx(many[1]["max_rel_error"], rel=1e-4)
    with pytest.raises(FileNotFoundError, match="episode: .*nothing.h5'] not found"):
        predict(cfg_for("predict", base + [f"episode={tmp_path / 'nothing.h5'}", f"out_dir={tmp_path / 'x'}"]))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no episode files"):
        predict(cfg_for("predict", base + [f"episode={tmp_path / 'empty'}", f"out_dir={tmp_path / 'x'}"]))


def test_bench_rollout_writes_a_row_per_setting_and_refuses_a_bad_one(trained, data_dir, tmp_path):  # noqa: F811
    run_dir, _ = trained
    base = [sys.executable, str(ROOT / "scripts" / "bench_rollout.py"), "--checkpoint", str(run_dir / "best.pt"),
            "--data-dir", str(data_dir), "--designs", "1", "--repeats", "1", "--out", str(tmp_path / "b")]
    r = subprocess.run(base + ["--settings", "1:false,2:true,1:false:4", "--batch", "3"], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = (tmp_path / "b" / "rollout.csv").read_text().splitlines()
    assert rows[0].startswith("backend,members,rotations,mirror,lattice_turns,copies,batch,ms_per_design")
    assert len(rows) == 7
    assert rows[3].startswith("torchscript,1,2,True,1,4,1,") and rows[4].startswith("torchscript,1,2,True,1,4,3,")
    assert rows[5].startswith("torchscript,1,1,False,4,4,1,") and rows[6].startswith("torchscript,1,1,False,4,4,3,")
    assert all(float(row.split(",")[7]) > 0 for row in rows[1:])
    assert (tmp_path / "b" / "rollout.png").stat().st_size > 0
    assert "Machine:" in (tmp_path / "b" / "rollout.md").read_text()
    for setting in ("0:false", "1:false:3", "1"):
        bad = subprocess.run(base + ["--settings", setting], capture_output=True, text=True, timeout=600)
        assert bad.returncode != 0 and "--settings" in bad.stderr
    bad = subprocess.run(base + ["--settings", "1:false", "--batch", "1"], capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "--batch 1: every count must be >= 2" in bad.stderr
    bad = subprocess.run(base + ["--backend", "torchscript,onnx"], capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "rollout_backend='onnx': must be one of torchscript | aot" in bad.stderr


def test_first_step_probe_writes_a_row_and_refuses_a_bad_frame_count(trained, data_dir, tmp_path):  # noqa: F811
    run_dir, _ = trained
    base = [sys.executable, str(ROOT / "scripts" / "first_step.py"), "--data-dir", str(data_dir),
            "--split-from", str(run_dir / "last.pt"), "--train-designs", "3", "--epochs", "2",
            "--out", str(tmp_path / "fs"), "rotations=2", "model.n_blocks=3"]
    r = subprocess.run(base, capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    header, row = (tmp_path / "fs" / "first_step.csv").read_text().splitlines()
    values = dict(zip(header.split(","), row.split(",")))
    assert values["overrides"] == "rotations=2 model.n_blocks=3" and values["frames"] == "2"
    assert 0 < float(values["train_error"]) < 1 and 0 < float(values["val_error"]) < 1
    assert float(values["fea_motion_val"]) > 0
    bad = subprocess.run(base + ["--frames", "1"], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert bad.returncode != 0 and "--frames=1" in bad.stderr
