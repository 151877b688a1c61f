"""learn.validity_calibration: thresholds of the validity check fitted to held-out reports (synthetic reports)."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from learn.validity_calibration import best_thresholds, calibrate, markdown

REPO = Path(__file__).resolve().parents[1]


def report(rows: list[tuple[float, float, float]], margin: float = 0.0, flag: float = 0.10) -> dict:
    """A learn.evaluate report of designs (max error, dislocation / size, out-of-range share)."""
    return {"validity_thresholds": {"range_margin": margin}, "validity_measured": {"flag_error_rel": flag},
            "designs": [{"name": f"e{i}", "max_rel_error": e, "valid": True,
                         "validity": {"max_dislocation_rel": d, "out_of_range_fraction": o}}
                        for i, (e, d, o) in enumerate(rows)]}


# the bad designs (error > 10 %) are those with more than 30 % of blocks out of range, or a dislocation over 4 %
ROWS = [(0.05, 0.010, 0.10), (0.06, 0.020, 0.20), (0.07, 0.030, 0.30), (0.08, 0.020, 0.25),
        (0.12, 0.015, 0.40), (0.15, 0.020, 0.60), (0.20, 0.050, 0.10), (0.09, 0.035, 0.00)]


def test_a_threshold_is_put_where_it_separates_the_bad_designs_from_the_good():
    errors = np.array([e for e, _, _ in ROWS])
    oor = np.array([o for _, _, o in ROWS])
    (tau,), out = best_thresholds([oor], errors, 0.10)
    assert tau == pytest.approx(0.30)  # flag above 30 %: both out-of-range bad designs, none of the good
    assert (out["caught"], out["n_bad"], out["false_flags"]) == (2, 3, 0)
    assert out["youden_j"] == pytest.approx(2 / 3)
    assert out["passed"]["worst"] == pytest.approx(0.20)  # the dislocated one slips through this rule alone


def test_the_pair_catches_what_each_indicator_misses_and_the_check_reports_measure_it_elsewhere():
    other = report([(0.05, 0.01, 0.5), (0.15, 0.06, 0.0), (0.25, 0.01, 0.9), (0.08, 0.02, 0.1)])
    result = calibrate([report(ROWS)], check=[other])
    assert result["error_rel"] == 0.10 and result["n_bad"] == 3 and result["range_margin"] == 0.0
    pair = result["rules"][-1]
    assert pair["indicators"] == ["max_dislocation_rel", "out_of_range_fraction"]
    assert pair["thresholds"] == pytest.approx([0.035, 0.30])  # the largest values that still leave no bad unflagged
    assert pair["fitted"]["youden_j"] == pytest.approx(1.0)
    assert (pair["check"]["caught"], pair["check"]["n_bad"], pair["check"]["false_flags"]) == (2, 2, 1)
    assert result["spearman"]["max_dislocation_rel"] > 0
    text = markdown(result)
    assert "max_dislocation_rel: 0.035" in text and "max_out_of_range: 0.3" in text


def test_the_lines_of_a_local_frame_model_go_under_its_section_of_conf():
    """A model.frame=local model is judged by conf/validity/default.yaml's `local:` thresholds (learn.validity.
    thresholds), so its calibration's lines are written under `local:`; reports of models in different frames are
    not pooled."""
    import yaml
    local = {**report(ROWS), "model": {"frame": "local", "update": "stiffness"}}
    text = markdown(calibrate([local]))
    block = yaml.safe_load(text.split("```yaml")[1].split("```")[0])
    assert block == {"local": {"max_dislocation_rel": pytest.approx(0.035), "max_out_of_range": pytest.approx(0.3)}}
    assert "under `local:`" in text
    glob = {**report(ROWS), "model": {"frame": "global"}}
    assert set(yaml.safe_load(markdown(calibrate([glob])).split("```yaml")[1].split("```")[0])) == {
        "max_dislocation_rel", "max_out_of_range"}
    with pytest.raises(ValueError, match="models of different frames"):
        calibrate([local, glob])
    ensemble = {**report(ROWS), "model": {"frame": "global", "member_args": [{"frame": "global"}, {"frame": "local"}]}}
    assert calibrate([ensemble])["frame"] == "local"  # as learn.validity.thresholds judges it


def test_reports_that_mean_different_things_or_no_bad_design_rule_are_refused():
    with pytest.raises(ValueError, match="different validity.range_margin"):
        calibrate([report(ROWS, margin=0.0), report(ROWS, margin=0.25)])
    with pytest.raises(ValueError, match="error_rel: the reports do not say"):
        calibrate([report(ROWS, flag=0.10), report(ROWS, flag=0.05)])
    with pytest.raises(ValueError, match=r"error_rel=1.5: must be a number in \(0, 1\) \(a fraction of the design"):
        calibrate([report(ROWS)], error_rel=1.5)
    with pytest.raises(ValueError, match="reports: give at least one"):
        calibrate([])


def test_the_command_writes_the_table_the_numbers_and_the_plot(tmp_path):
    src = tmp_path / "a"
    src.mkdir()
    (src / "report.json").write_text(json.dumps(report(ROWS)))
    out = tmp_path / "cal"
    subprocess.run([sys.executable, "-m", "learn.validity_calibration", f"reports=[{src}]", f"out_dir={out}"],
                   cwd=REPO, check=True, capture_output=True)
    result = json.loads((out / "calibration.json").read_text())
    assert result["rules"][-1]["thresholds"] == pytest.approx([0.035, 0.30])
    assert "max_out_of_range: 0.3" in (out / "calibration.md").read_text()
    assert (out / "calibration.png").stat().st_size > 0


def test_the_check_defaults_are_the_calibrated_thresholds_of_conf():
    """learn.validity.check's keyword defaults (used by callers that pass no config) equal conf/validity/default.yaml,
    the one place the calibrated thresholds are kept."""
    import inspect

    from omegaconf import OmegaConf

    from learn.validity import check
    conf = OmegaConf.to_container(OmegaConf.load(REPO / "conf" / "validity" / "default.yaml"))
    conf = {k: v for k, v in conf.items() if not isinstance(v, dict)}  # the per-frame overrides aside
    defaults = {k: p.default for k, p in inspect.signature(check).parameters.items() if k in conf}
    assert defaults == conf


def test_a_model_in_local_frames_is_judged_by_the_thresholds_calibrated_for_that_frame():
    """learn.validity.thresholds: a global model gets conf/validity's top-level thresholds, a model.frame=local one (or
    an ensemble with such a member) those under `local:`; an override that names no threshold is refused."""
    import inspect

    from omegaconf import OmegaConf

    from data_schema.testing import synthetic_episode
    from learn.dataset import GraphSet
    from learn.ensemble import Ensemble
    from learn.features import extract
    from learn.model import Simulator
    from learn.validity import check, thresholds
    conf = OmegaConf.to_container(OmegaConf.load(REPO / "conf" / "validity" / "default.yaml"))
    data = GraphSet.build([extract(synthetic_episode(3, 3, 5, 3, 3, frames=3, seed=0), name="ep0.h5")])
    models = {frame: Simulator.fit({"core": "double_gn", "latent": 4, "widths": [8], "frame": frame},
                                   data.joint_state, data.beam_state, data.static) for frame in ("global", "local")}
    plain, local = thresholds(conf, models["global"]), thresholds(conf, models["local"])
    assert plain["max_out_of_range"] == conf["max_out_of_range"] and "local" not in plain
    assert local["max_out_of_range"] == conf["local"]["max_out_of_range"] != conf["max_out_of_range"]
    assert {k: v for k, v in local.items() if k not in conf["local"]} == {
        k: v for k, v in plain.items() if k not in conf["local"]}
    assert thresholds(conf, Ensemble([models["global"], models["local"]])) == local
    assert set(local) <= set(inspect.signature(check).parameters)
    with pytest.raises(ValueError, match="validity.local: unknown thresholds.*max_out_of_rang"):
        thresholds({**conf, "local": {"max_out_of_rang": 0.5}}, models["local"])
    with pytest.raises(ValueError, match="validity.locl: not a model frame"):
        thresholds({**conf, "locl": {"max_out_of_range": 0.5}}, models["global"])
    fixed = Simulator.fit({"core": "double_gn", "latent": 4, "widths": [8], "frame": "fixed"}, data.joint_state,
                          data.beam_state, data.static)
    with pytest.raises(ValueError, match=r"frames \['fixed', 'local'\]: no one section"):  # the same rule as reports'
        thresholds(conf, Ensemble([models["local"], fixed]))
    from learn.validity_calibration import model_frame
    with pytest.raises(ValueError, match=r"frames \['fixed', 'local'\]: no one section"):
        model_frame({"member_args": [{"frame": "local"}, {"frame": "fixed"}, {"frame": "global"}]})
    assert model_frame({"member_args": [{"frame": "local"}, {}]}) == "local" and model_frame({}) == "global"


def test_an_answer_of_a_one_kind_design_that_has_not_rolled_is_the_unrolled_indicator():
    """learn.validity.unrolled_one_kind: 1 - |s_i - s_j| (s: final extents along the lattice's i, j / flat ones) for
    all-up or all-down designs, 0 for mixed ones; the check flags its last frame above max_unrolled_one_kind."""
    from dataclasses import replace

    from data_schema.testing import synthetic_episode
    from learn.features import extract
    from learn.rollout import reference
    from learn.validity import unrolled_one_kind

    ep = synthetic_episode(3, 3, 5, 3, 3, frames=3, seed=0)
    ep.beam_kind[:] = 1  # all down
    r = reference(extract(ep))
    flat = r.points[0]
    rolled = flat.copy()
    rolled[:, 0] = flat[:, 0].min() + 0.4 * (flat[:, 0] - flat[:, 0].min())  # x extent to 40 %, y kept: a roll
    bowl = flat.copy()
    bowl[:, :2] = flat[:, :2].min(0) + 0.8 * (flat[:, :2] - flat[:, :2].min(0))  # both to 80 %: no roll
    assert unrolled_one_kind(replace(r, points=np.stack([flat, rolled]))) == pytest.approx(0.4)
    assert unrolled_one_kind(replace(r, points=np.stack([flat, bowl]))) == pytest.approx(1.0)
    ep.beam_kind[0] = 0  # one up among the downs: mixed, no such branch
    assert unrolled_one_kind(replace(reference(extract(ep)), points=np.stack([flat, bowl]))) == 0.0


def test_a_local_model_flags_every_one_kind_design_however_its_answer_rolled():
    """conf/validity `local: max_unrolled_one_kind: 0` (session 36): a one-kind design sits at a bifurcation, so its
    answer is flagged even when it has rolled fully one way, with the reason naming the bifurcation; a mixed design's
    indicator is 0 and never trips it."""
    from dataclasses import replace

    from omegaconf import OmegaConf

    from data_schema.testing import synthetic_episode
    from learn.dataset import GraphSet
    from learn.features import extract
    from learn.model import Simulator
    from learn.rollout import reference
    from learn.validity import check, thresholds

    conf = OmegaConf.to_container(OmegaConf.load(REPO / "conf" / "validity" / "default.yaml"))
    ep = synthetic_episode(3, 3, 5, 3, 3, frames=3, seed=0)
    ep.beam_kind[:] = 1  # all down
    one_kind = extract(ep)
    data = GraphSet.build([one_kind])
    model = Simulator.fit({"core": "double_gn", "latent": 4, "widths": [8], "frame": "local"},
                          data.joint_state, data.beam_state, data.static)
    limits = {**thresholds(conf, model), "max_dislocation_rel": 1e9, "max_out_of_range": 1.0}  # this indicator alone
    assert limits["max_unrolled_one_kind"] == 0
    r = reference(one_kind)
    flat = r.points[0]
    rolled = flat.copy()
    lo, span = flat[:, 0].min(), np.ptp(flat[:, 0])
    rolled[:, 0] = lo + 0.05 * (flat[:, 0] - lo)  # x extent to 5 %, y kept: rolled almost fully one way
    verdict = check(model, replace(r, points=np.stack([flat, flat, rolled])), **limits)
    assert verdict.unrolled_one_kind == pytest.approx(0.05, abs=1e-6) and span > 0
    assert not verdict.valid and verdict.first_bad_frame == 2
    assert "all actuators down: a bifurcation" in verdict.reasons[0]
    ep.beam_kind[0] = 0  # one up among the downs: mixed
    mixed = reference(extract(ep))
    verdict = check(model, replace(mixed, points=np.stack([flat, flat, rolled])), **limits)
    assert verdict.unrolled_one_kind == 0.0 and verdict.valid


def test_the_roll_is_measured_along_the_lattice_whatever_its_angle_to_x():
    """A grid turned 45 deg about z that rolls along its lattice direction i shrinks alike along x and y: measured
    along x and y (as before session 31) it would pass as unrolled (1 - |s_x - s_y| near 1); along the lattice
    (learn.roll) it is rolled, and a bowl still is not."""
    from dataclasses import replace

    from data_schema.testing import synthetic_episode
    from learn.features import extract
    from learn.roll import lattice_directions, roll
    from learn.rollout import reference
    from learn.validity import unrolled_one_kind

    ep = synthetic_episode(3, 3, 5, 3, 3, frames=3, seed=0)
    ep.beam_kind[:] = 0  # all up
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    f = extract(ep).rotated(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))
    r = reference(f)
    ui, uj = lattice_directions(f)
    assert abs(abs(ui @ np.array([c, s])) - 1) < 1e-6  # i turned with the design
    flat = r.points[0]
    rolled = flat.copy()
    rolled[:, :2] -= 0.6 * np.outer((flat[:, :2] - flat[:, :2].min(0)) @ ui, ui)  # i extent to 40 %, j kept
    xy = np.ptp(rolled[:, :2], 0) / np.ptp(flat[:, :2], 0)
    assert 1 - abs(xy[0] - xy[1]) > 0.95  # along x and y it looks unrolled
    assert roll(f, np.stack([flat, rolled])) == pytest.approx(-0.6)
    assert unrolled_one_kind(replace(r, points=np.stack([flat, rolled]))) == pytest.approx(0.4)
    bowl = flat.copy()
    bowl[:, :2] *= 0.8
    assert unrolled_one_kind(replace(r, points=np.stack([flat, bowl]))) == pytest.approx(1.0)


def test_a_third_indicator_joins_the_joint_rule_when_it_catches_what_the_others_miss():
    rows = ROWS + [(0.30, 0.01, 0.05)]  # a bad design both miss ...
    rep = report(rows)
    for d, unrolled in zip(rep["designs"], [0.0] * len(ROWS) + [0.97]):  # ... and the roll indicator sees
        d["validity"]["unrolled_one_kind"] = unrolled
    joint = calibrate([rep])["rules"][-1]
    assert joint["indicators"] == ["max_dislocation_rel", "out_of_range_fraction", "unrolled_one_kind"]
    assert joint["thresholds"] == pytest.approx([0.035, 0.30, 0.0]) and joint["fitted"]["youden_j"] == 1.0
    rep["designs"][-1]["validity"]["unrolled_one_kind"] = 0.0  # it sees nothing: left at never
    joint = calibrate([rep])["rules"][-1]
    assert joint["thresholds"][2] == np.inf and "max_unrolled_one_kind: 1" in markdown(calibrate([rep]))
