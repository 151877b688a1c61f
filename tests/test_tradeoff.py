"""Speed/accuracy trade: the tolerance pick on synthetic tables, the Pareto front, aggregation, solver.tolerance in
the composed config and on the CLIs (one tiny coarse solve), and the learned-rollout corner mapping."""
from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from fea_factory.tradeoff import (INCREMENT_MODES, TABLE_COLUMNS, Setting, TradeoffError, aggregate, apply_tolerance,
                                  parse_tolerance, pareto_front, pick, read_table, write_table)

ROOT = Path(__file__).resolve().parent.parent


def row(mesh, wall, err, increments="adaptive", linear="direct", ranks=1, reference=0, n_ok=2):
    s = Setting(mesh, increments, linear, ranks)
    return {"setting": s.name, "mesh": mesh, "increments": increments, "linear_solver": linear, "ranks": ranks,
            "n_designs": 2, "n_ok": n_ok, "wall_s": float(wall), "max_rel_error": float(err),
            "mean_rel_error": float(err) / 3, "newton": 50.0, "peak_mb": 100.0, "reference": reference}


TABLE = [row("coarse", 4.0, 0.04, "fixed10"), row("coarse", 5.0, 0.035), row("default", 9.0, 0.012),
         row("default", 12.0, 0.008, linear="iterative"), row("default", 6.0, 0.009, ranks=2),
         row("fine", 60.0, 0.0, reference=1), row("fine", 40.0, 1e-7, ranks=2, reference=1),
         row("coarse", 1.0, math.inf, "fixed20", n_ok=1)]  # failed on one design


@pytest.mark.parametrize("tol, want", [(0.05, "coarse/fixed10/direct/n1"), (0.04, "coarse/fixed10/direct/n1"),
                                       (0.036, "coarse/adaptive/direct/n1"), (0.02, "default/adaptive/direct/n1"),
                                       (0.01, "default/adaptive/iterative/n1"),
                                       ("1%", "default/adaptive/iterative/n1")])
def test_pick_is_the_cheapest_setting_meeting_the_tolerance(tol, want):
    assert pick(TABLE, tol, ranks=1)["setting"] == want


def test_pick_prefers_rows_of_the_episode_rank_count_and_falls_back_to_all():
    assert pick(TABLE, 0.01, ranks=2)["setting"] == "default/adaptive/direct/n2"
    assert pick(TABLE, 0.05, ranks=2)["setting"] == "default/adaptive/direct/n2"  # the only n2 row meeting it
    assert pick(TABLE, 0.05, ranks=4)["setting"] == "coarse/fixed10/direct/n1"  # no n4 rows: all rows
    assert pick(TABLE, 0.0085, ranks=2)["setting"] == "default/adaptive/iterative/n1"  # no n2 row meets it
    assert pick(TABLE, 0.05)["setting"] == "coarse/fixed10/direct/n1"


def test_pick_never_takes_the_reference_mesh_or_a_failed_setting():
    with pytest.raises(TradeoffError) as e:
        pick(TABLE, 0.005, ranks=1)
    msg = str(e.value)
    assert "solver.tolerance = 0.005" in msg and "0.008" in msg and "0.04" in msg  # the achievable range
    assert "default/adaptive/iterative/n1" in msg  # the most accurate measured setting
    with pytest.raises(TradeoffError, match="solver.tolerance"):
        pick([row("fine", 1.0, 0.0, reference=1), row("coarse", 1.0, math.inf)], 0.5)


def test_pick_ties_smaller_error_then_name():
    t = [row("default", 5.0, 0.01, linear="iterative"), row("default", 5.0, 0.008), row("coarse", 5.0, 0.008)]
    assert pick(t, 0.02)["setting"] == "coarse/adaptive/direct/n1"
    assert pick(t[:2], 0.02)["setting"] == "default/adaptive/direct/n1"
    assert pick(t[::-1], 0.02)["setting"] == pick(t, 0.02)["setting"]


@pytest.mark.parametrize("bad", [0, 0.0, 1, 1.5, -0.01, "abc", "%", "150%", True, float("nan"), float("inf"), None,
                                 [0.01]])
def test_invalid_tolerance_is_a_clear_error(bad):
    with pytest.raises(TradeoffError, match=r"solver\.tolerance = .*must be .* in \(0, 1\)"):
        parse_tolerance(bad)


def test_tolerance_spellings():
    assert parse_tolerance("1%") == pytest.approx(0.01) and parse_tolerance(" 0.5 %") == pytest.approx(0.005)
    assert parse_tolerance(0.02) == 0.02 and parse_tolerance("0.02") == 0.02


def test_pareto_front():
    cost = [1.0, 2.0, 3.0, 2.0, 0.5, 5.0, float("nan"), 3.0]
    err = [0.10, 0.05, 0.05, 0.08, 0.30, 0.01, 0.0, 0.01]
    assert pareto_front(cost, err).tolist() == [True, True, False, False, True, False, False, True]
    # identical points: only the first; nothing dominates the cheapest or the most accurate
    assert pareto_front([1, 1, 2], [0.1, 0.1, 0.2]).tolist() == [True, False, False]
    assert pareto_front([], []).tolist() == []


def test_aggregate_worst_error_mean_time_and_failures():
    rows = [{"setting": "a", "mesh": "coarse", "increments": "adaptive", "linear_solver": "direct", "ranks": 1,
             "status": "ok", "wall_s": w, "max_rel_error": e, "mean_rel_error": e / 2, "newton": 10, "peak_mb": m}
            for w, e, m in ((2.0, 0.01, 100), (4.0, 0.03, 150))]
    rows.append({**rows[0], "setting": "b", "mesh": "fine"})
    rows.append({**rows[0], "setting": "c", "status": "diverged", "max_rel_error": float("nan")})
    rows.append({**rows[0], "setting": "c"})
    t = {r["setting"]: r for r in aggregate(rows, reference_mesh="fine")}
    assert t["a"]["max_rel_error"] == 0.03 and t["a"]["wall_s"] == 3.0 and t["a"]["peak_mb"] == 150
    assert t["a"]["mean_rel_error"] == pytest.approx(0.01) and t["a"]["n_ok"] == 2 and not t["a"]["reference"]
    assert t["b"]["reference"] == 1
    assert t["c"]["n_ok"] == 1 and t["c"]["max_rel_error"] == math.inf  # never picked


def test_table_round_trip_and_missing_table(tmp_path):
    path = write_table(tmp_path / "t.csv", TABLE, ["provenance line"])
    assert path.read_text().startswith("# provenance line\n" + ",".join(TABLE_COLUMNS))
    back = read_table(path)
    assert [r["setting"] for r in back] == [r["setting"] for r in TABLE]
    assert pick(back, 0.02, ranks=1)["setting"] == pick(TABLE, 0.02, ranks=1)["setting"]
    with pytest.raises(TradeoffError, match="make tradeoff INSTALL=1"):
        read_table(tmp_path / "none.csv")


def _compose(config_name: str, *overrides: str):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name=config_name, overrides=list(overrides))


@pytest.mark.parametrize("mode", sorted(INCREMENT_MODES))
def test_every_setting_composes_to_valid_settings_with_11_frames(mode):
    from fea_factory.mesh import MeshPreset
    from fea_factory.solver import SolverSettings

    for lin in ("direct", "iterative"):
        cfg = _compose("solve", "design=x", "out=y", *Setting("coarse", mode, lin).overrides())
        s = SolverSettings.from_mapping(cfg.solver)
        assert len(s.frame_times) == 11 and s.linear_solver == lin
        assert MeshPreset.from_mapping(cfg.mesh).name == "coarse"


def test_solver_tolerance_in_the_composed_config(tmp_path):
    from fea_factory.mesh import MeshPreset
    from fea_factory.solver import SolverSettings

    table = write_table(tmp_path / "t.csv", TABLE)
    cfg = _compose("solve", "design=x", "out=y")
    assert cfg.solver.tolerance is None and apply_tolerance(cfg, table=table) is None
    cfg = _compose("generate", "solver.tolerance=2%", "mesh=fine")  # the tolerance overrides the hand-picked preset
    rec = apply_tolerance(cfg, ranks=1, table=table)
    assert rec["setting"] == "default/adaptive/direct/n1" and rec["tolerance"] == pytest.approx(0.02)
    assert cfg.mesh.name == "default" and cfg.mesh.nodes_length == 9 and MeshPreset.from_mapping(cfg.mesh)
    assert cfg.solver.tolerance_pick.setting == rec["setting"]
    cfg = _compose("solve", "design=x", "out=y", "solver.tolerance=0.05", f"+solver.tolerance_table={table}")
    assert apply_tolerance(cfg)["setting"] == "coarse/fixed10/direct/n1"
    s = SolverSettings.from_mapping(cfg.solver)
    assert (s.adaptive, s.increments, s.save_every, cfg.mesh.name) == (False, 10, 1, "coarse")
    cfg = _compose("solve", "design=x", "out=y", "solver.tolerance=0.001", f"+solver.tolerance_table={table}")
    with pytest.raises(TradeoffError, match="solver.tolerance = 0.001: no measured FEA setting"):
        apply_tolerance(cfg)


def test_generate_refuses_an_unmeetable_or_invalid_tolerance_before_any_solve(tmp_path):
    from fea_factory.generate import check_config

    table = write_table(tmp_path / "t.csv", TABLE)
    with pytest.raises(ValueError, match="solver.tolerance = 1e-09"):
        check_config(_compose("generate", "solver.tolerance=1e-9", f"+solver.tolerance_table={table}"))
    r = subprocess.run([sys.executable, "-m", "fea_factory.generate", f"out={tmp_path / 'ds'}", "n=1",
                        "progress=false", "solver.tolerance=-1"], cwd=ROOT, capture_output=True, text=True,
                       stdin=subprocess.DEVNULL, timeout=300)
    assert r.returncode == 2 and "solver.tolerance = -1" in r.stderr
    assert not list((tmp_path / "ds").glob("*.h5"))


def test_solve_cli_picks_from_the_table_and_records_it(tmp_path):
    """The one FEA solve here: a two-joint strip on the coarse preset picked by solver.tolerance."""
    pytest.importorskip("dolfinx")
    from data_schema.episode import read_episode
    from fea_factory.design import Design

    table = write_table(tmp_path / "t.csv", TABLE)
    design = Design([[0, 0], [1, 0]], [[0.0, 0.0], [47.2, 0.0]], [[0, 1]], ["up"], 0)
    design.save(tmp_path / "d.json")
    cmd = [sys.executable, "-m", "fea_factory.solve", f"design={tmp_path / 'd.json'}", f"out={tmp_path / 'ep.h5'}",
           f"+solver.tolerance_table={table}"]
    bad = subprocess.run(cmd + ["solver.tolerance=abc"], cwd=ROOT, capture_output=True, text=True,
                         stdin=subprocess.DEVNULL, timeout=300)
    assert bad.returncode == 2 and "solver.tolerance = 'abc'" in bad.stderr
    r = subprocess.run(cmd + ["solver.tolerance=5%"], cwd=ROOT, capture_output=True, text=True,
                       stdin=subprocess.DEVNULL, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    ep = read_episode(tmp_path / "ep.h5")
    assert ep.preset == "coarse" and len(ep.t) == 11 and ep.solver_stats["increments"] == 10
    assert "setting: coarse/fixed10/direct/n1" in ep.config_yaml and "tolerance: 0.05" in ep.config_yaml


def load_script():
    if "tradeoff_script" not in sys.modules:
        spec = importlib.util.spec_from_file_location("tradeoff_script", ROOT / "scripts" / "tradeoff.py")
        script = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = script  # dataclasses look their module up
        spec.loader.exec_module(script)
    return sys.modules["tradeoff_script"]


def test_report_plot_summary_and_install_from_synthetic_rows(tmp_path):
    import argparse

    script = load_script()
    rows = []
    for design, scale in (("a", 1.0), ("b", 1.5)):
        for s, wall, err, status in ((Setting("fine"), 100, 0.0, "ok"), (Setting("coarse"), 5, 0.03, "ok"),
                                     (Setting("default"), 10, 0.01, "ok"), (Setting("medium"), 20, 0.004, "ok"),
                                     (Setting("default", "fixed10"), math.nan, math.nan, "diverged"),
                                     (Setting("fine", ranks=2), 70, 1e-8, "ok")):
            rows.append({"design": design, "setting": s.name, "kind": "fea", "mesh": s.mesh,
                         "increments": s.increments, "linear_solver": s.linear_solver, "ranks": s.ranks,
                         "status": status, "wall_s": wall * scale, "newton": 50, "peak_mb": 300.0,
                         "max_rel_error": err * scale, "mean_rel_error": err * scale / 3, "max_error_mm": err,
                         "reason": ""})
        rows.append({**rows[-1], "setting": "learned:x/best", "kind": "learned", "mesh": "", "increments": "",
                     "linear_solver": "", "ranks": 1, "wall_s": 0.003, "max_rel_error": 0.02 * scale,
                     "mean_rel_error": 0.005, "newton": math.nan, "peak_mb": None})
    table = script.summarize(rows, Setting("fine"), "fine")
    by = {t["setting"]: t for t in table}
    assert by["learned:x/best"]["pareto"] and by["medium/adaptive/direct/n1"]["pareto"]
    assert not by["fine/adaptive/direct/n1"]["pareto"] and not by["default/fixed10/direct/n1"]["pareto"]
    assert script.cheapest(table, 0.01, fea_only=True)["setting"] == "medium/adaptive/direct/n1"
    assert script.cheapest(table, 0.05, fea_only=False)["setting"] == "learned:x/best"
    assert script.cheapest(table, 0.001, fea_only=True) is None
    script.plot(table, tmp_path, Setting("fine"))
    assert (tmp_path / "pareto.png").stat().st_size > 10_000
    args = argparse.Namespace(panel="reduced", note="")
    md = script.markdown(rows, table, [], Setting("fine"), args, 1.0, "0/0/0", "0/0/0", "none")
    assert "| 1 % | `medium/adaptive/direct/n1` | 25 | 0.6 % |" in md and "| 0.5 % | none measured |" in md
    script.write_csv(tmp_path / "t.csv", rows)
    path = write_table(tmp_path / "table.csv", [t for t in table if t["kind"] == "fea"])
    assert pick(read_table(path), 0.02)["setting"] == "default/adaptive/direct/n1"


def test_csv_round_trip_for_resume_gives_the_same_summary(tmp_path):
    script = load_script()
    rows = [{"design": "a", "design_size_mm": 120.0, "setting": s.name, "kind": "fea", "mesh": s.mesh,
             "increments": s.increments, "linear_solver": s.linear_solver, "ranks": s.ranks, "status": status,
             "wall_s": wall, "process_s": wall + 1.0, "newton": 50.0, "peak_mb": 300.0, "max_rel_error": err,
             "mean_rel_error": err / 3, "max_error_mm": err * 120.0, "reason": reason}
            for s, wall, err, status, reason in ((Setting("fine"), 100.0, 0.0, "ok", ""),
                                                 (Setting("coarse"), 5.0, 0.03, "ok", ""),
                                                 (Setting("default", ranks=2), 8.0, 0.01, "ok", ""),
                                                 (Setting("default", "fixed10"), math.nan, math.nan, "diverged",
                                                  "residual is NaN/Inf"))]
    script.write_csv(tmp_path / "t.csv", rows)
    back = script.read_csv(tmp_path / "t.csv")
    assert [r["status"] for r in back] == ["ok", "ok", "ok", "diverged"] and back[2]["ranks"] == 2
    assert math.isnan(back[3]["wall_s"]) and back[3]["reason"] == "residual is NaN/Inf"
    want = script.summarize(rows, Setting("fine"), "fine")
    got = script.summarize(back, Setting("fine"), "fine")
    assert [(t["setting"], t["pareto"]) for t in got] == [(t["setting"], t["pareto"]) for t in want]
    for a, b in zip(got, want):
        assert a["max_rel_error"] == pytest.approx(b["max_rel_error"], rel=1e-3, nan_ok=True)
        assert a["wall_s"] == pytest.approx(b["wall_s"], rel=1e-3, nan_ok=True)


def test_learned_row_compares_the_rollout_joint_corners(tmp_path):
    """scripts/tradeoff.py's learned rows on a synthetic episode with an (untrained) fitted simulator."""
    torch = pytest.importorskip("torch")
    from data_schema.testing import synthetic_episode
    from fea_factory.compare import corner_nodes
    from learn.features import JOINT_POINTS, extract
    from learn.model import Simulator, static_from

    script = load_script()
    ep = synthetic_episode(3, 3, 5, 3, 3, frames=4, seed=1)
    f = extract(ep)
    model = Simulator.fit({"core": "double_gn", "latent": 8, "widths": [16, 8], "time_input": True},
                          torch.as_tensor(f.joint_state), torch.as_tensor(f.beam_state),
                          static_from(f.joint_bc, f.beam_bc, f.incidence)).eval()
    r = script.learned_row(model, ep, "learned:test", "synthetic", float(ep.design_size), repeats=1)
    assert r["status"] == "ok" and r["kind"] == "learned" and r["wall_s"] > 0
    assert np.isfinite(r["max_rel_error"]) and 0 <= r["mean_rel_error"] <= r["max_rel_error"]
    idx = script.corner_point_index(f.point_nodes, corner_nodes(ep))
    assert (f.point_nodes[idx] == corner_nodes(ep)).all()
    assert (idx < len(ep.joint_nodes) * len(JOINT_POINTS)).all()  # the joints' own predictions, not beam end faces


def test_time_cap_is_the_fastest_run_on_a_mesh_at_least_as_fine():
    script = load_script()
    done = [(Setting("fine"), 300.0), (Setting("coarse"), 15.0), (Setting("default"), 27.0)]
    assert script.time_cap(Setting("default", "fixed10"), done, 1.5) == (40.5, Setting("default"))
    assert script.time_cap(Setting("coarse", linear_solver="iterative"), done, 1.0) == (15.0, Setting("coarse"))
    assert script.time_cap(Setting("medium", ranks=2), done, 1.0) == (300.0, Setting("fine"))
    assert script.time_cap(Setting("fine"), [], 1.0) is None
