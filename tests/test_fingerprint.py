"""data_schema.fingerprint: a regenerated data set is checked against the fingerprints of the one measured on."""
import json

import numpy as np
import pytest

from data_schema.episode import write_episode
from data_schema.fingerprint import COLUMNS, differences, fingerprint, main, read_fingerprints
from data_schema.testing import synthetic_episode


@pytest.fixture
def data_dir(tmp_path):
    d = tmp_path / "ds"
    for i in range(2):
        write_episode(d / f"episode_{i:05d}.h5", synthetic_episode(seed=i))
    return d


def test_row_holds_the_final_shape(data_dir):
    ep = synthetic_episode(seed=1)
    row = fingerprint(data_dir / "episode_00001.h5")
    u = np.linalg.norm(ep.node_xyz[-1].astype(np.float64) - ep.node_xyz0, axis=1)
    assert row["final_max_disp_mm"] == pytest.approx(u.max(), rel=1e-12)
    assert row["final_rms_disp_mm"] == pytest.approx(np.sqrt((u ** 2).mean()), rel=1e-12)
    assert row["final_centroid_z_mm"] == pytest.approx(ep.node_xyz[-1, :, 2].astype(np.float64).mean(), rel=1e-12)
    assert (row["n_nodes"], row["n_cells"], row["n_frames"]) == (ep.n_nodes, ep.n_cells, ep.n_frames)
    assert row["final_max_disp_mm"] > 1.0  # the synthetic morph moves the grid: the numbers say something


def test_design_digest_ignores_key_order(tmp_path):
    ep = synthetic_episode(seed=3)
    shuffled = json.dumps(dict(reversed(list(json.loads(ep.design_json).items()))))
    write_episode(tmp_path / "a.h5", ep)
    write_episode(tmp_path / "b.h5", ep.replace(design_json=shuffled))
    assert fingerprint(tmp_path / "a.h5")["design_sha256"] == fingerprint(tmp_path / "b.h5")["design_sha256"]


def test_same_data_passes_and_a_moved_node_fails(data_dir, tmp_path, capsys):
    ref = tmp_path / "fp.csv"
    assert main([str(data_dir), "--write", str(ref)]) == 0
    assert main([str(data_dir), "--check", str(ref)]) == 0
    ep = synthetic_episode(seed=1)
    moved = ep.node_xyz.copy()
    moved[-1] = moved[0] + 1.002 * (moved[-1] - moved[0])  # the final displacement 0.2 % larger: the solve changed
    write_episode(data_dir / "episode_00001.h5", ep.replace(node_xyz=moved))
    capsys.readouterr()
    assert main([str(data_dir), "--check", str(ref)]) == 1
    out = capsys.readouterr().out
    assert "episode_00001.h5: final_max_disp_mm" in out and "episode_00000" not in out
    assert main([str(data_dir), "--check", str(ref), "--tol-mm", "1.0"]) == 0


def test_another_design_is_named(data_dir, tmp_path):
    ref = tmp_path / "fp.csv"
    main([str(data_dir), "--write", str(ref)])
    write_episode(data_dir / "episode_00000.h5", synthetic_episode(seed=7))
    problems = differences(read_fingerprints(ref), [fingerprint(data_dir / "episode_00000.h5")])
    assert len(problems) == 1 and problems[0].startswith("episode_00000.h5: design_sha256: another design")


def test_a_design_written_with_other_last_bits_and_the_same_shape_is_round_off_not_a_difference(data_dir, tmp_path,
                                                                                                capsys):
    """Another CPU's sampler rounds a coordinate's last bit otherwise: another digest, the same FEA answer."""
    ref = tmp_path / "fp.csv"
    main([str(data_dir), "--write", str(ref)])
    ep = synthetic_episode(seed=0)
    design = json.loads(ep.design_json)
    x = design["joints"][0]["xy"][0]
    design["joints"][0]["xy"][0] = float(np.nextafter(x, np.inf))  # one ulp
    write_episode(data_dir / "episode_00000.h5", ep.replace(design_json=json.dumps(design)))
    capsys.readouterr()
    assert main([str(data_dir), "--check", str(ref)]) == 0
    out = capsys.readouterr().out
    assert "ROUND-OFF episode_00000.h5: design_sha256" in out and "DIFFERS" not in out


def test_partial_data_is_checked_as_far_as_it_goes(data_dir, tmp_path):
    ref = tmp_path / "fp.csv"
    main([str(data_dir), "--write", str(ref)])
    (data_dir / "episode_00001.h5").unlink()
    assert main([str(data_dir), "--check", str(ref)]) == 0


def test_bad_inputs_are_named(data_dir, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("episode,design_sha256\nepisode_00000.h5,abc\n")
    with pytest.raises(ValueError, match="lacks column"):
        read_fingerprints(bad)
    with pytest.raises(ValueError, match="tol_mm"):
        differences({}, [], tol_mm=-1.0)
    with pytest.raises(SystemExit):
        main([str(tmp_path / "nowhere"), "--check", str(bad)])
    with pytest.raises(SystemExit):
        main([str(data_dir), "--check", str(bad), "--tol-mm", "-0.1"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit):
        main([str(tmp_path / "empty"), "--check", str(bad)])
    assert set(COLUMNS) >= {"episode", "design_sha256", "final_max_disp_mm"}
