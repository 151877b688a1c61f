"""learn.compare: design-by-design comparison of reports (synthetic reports; no training)."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from learn.compare import compare, markdown

REPO = Path(__file__).resolve().parents[1]


def report(errors: dict[str, float], data_dir="data/a") -> dict:
    return {"data_dir": data_dir, "designs": [{"name": n, "max_rel_error": e} for n, e in errors.items()]}


def test_counts_and_median_ratio_are_per_design():
    base = report({"d0": 0.10, "d1": 0.20, "d2": 0.40, "d3": 0.05})
    other = report({"d3": 0.10, "d2": 0.20, "d1": 0.10, "d0": 0.05})  # another order: paired by name
    out = compare([base, other], ["base", "other"])
    row = out["rows"][1]
    assert (row["better_on"], row["worse_on"]) == (3, 1)
    assert row["median_ratio"] == pytest.approx(np.median([0.5, 0.5, 0.5, 2.0]))
    assert out["rows"][0]["median"] == pytest.approx(0.15) and row["worst"] == pytest.approx(0.20)
    assert out["base_worst_designs"][0]["name"] == "d2" and out["base_worst_designs"][0]["errors"] == [0.40, 0.20]
    assert "3 of 4 (worse on 1) | x0.500" in markdown(out)


def test_pooled_designs_are_told_apart_by_their_data_set():
    """learn.combine reports carry each design's data_dir: the same episode name in two data sets is two designs."""
    pooled = {"data_dir": "a, b", "designs": [{"name": "e0", "data_dir": "a", "max_rel_error": 0.1},
                                              {"name": "e0", "data_dir": "b", "max_rel_error": 0.3}]}
    other = {"data_dir": "a, b", "designs": [{"name": "e0", "data_dir": "b", "max_rel_error": 0.1},
                                             {"name": "e0", "data_dir": "a", "max_rel_error": 0.2}]}
    row = compare([pooled, other], ["p", "o"])["rows"][1]
    assert (row["better_on"], row["worse_on"], row["n"]) == (1, 1, 2)


def test_reports_over_other_designs_or_too_few_are_refused():
    with pytest.raises(ValueError, match="other designs than a .*missing 1"):
        compare([report({"d0": 0.1, "d1": 0.2}), report({"d0": 0.1})], ["a", "b"])
    with pytest.raises(ValueError, match="at least 2"):
        compare([report({"d0": 0.1})], ["a"])
    with pytest.raises(ValueError, match="labels: 1 given for 2"):
        compare([report({"d0": 0.1}), report({"d0": 0.1})], ["a"])


def test_cli_writes_table_json_and_plot(tmp_path):
    for name, errs in (("a", {"d0": 0.1, "d1": 0.2, "d2": 0.3}), ("b", {"d0": 0.05, "d1": 0.3, "d2": 0.1})):
        (tmp_path / name).mkdir()
        (tmp_path / name / "report.json").write_text(json.dumps(report(errs)))
    subprocess.run([sys.executable, "-m", "learn.compare", f"reports=[{tmp_path / 'a'},{tmp_path / 'b'}]",
                    "labels=[old,new]", f"out_dir={tmp_path / 'cmp'}"], cwd=REPO, check=True, capture_output=True)
    result = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert result["rows"][1]["label"] == "new" and result["rows"][1]["better_on"] == 2
    assert (tmp_path / "cmp" / "compare.png").stat().st_size > 0 and (tmp_path / "cmp" / "compare.md").exists()


def history(val, train=None, seconds_per_epoch=100.0):
    return [{"epoch": e, "val_rollout": v, "seconds": seconds_per_epoch * (e + 1),
             **({} if train is None else {"train_rollout": train[e]})} for e, v in enumerate(val)]


def test_curves_rows_hold_each_runs_best_when_it_came_and_the_settings_that_differ():
    from learn.curves import curves, markdown
    fast = ("fast", history([0.2, 0.1, 0.12], [0.1, 0.05, 0.04], seconds_per_epoch=36.0),
            {"batch_size": 64, "precision": "bf16", "seed": 0, "optim": {"lr": 2e-3}})
    slow = ("slow", history([0.3, 0.2, 0.15, 0.09]), {"batch_size": 16, "seed": 0, "optim": {"lr": 1e-3}})
    out = curves([fast, slow])
    assert out["differs"] == ["batch_size", "precision", "optim.lr"]
    f, s = out["rows"]
    assert (f["best_val_rollout"], f["best_epoch"], f["train_rollout_at_best"]) == (0.1, 1, 0.05)
    assert f["best_hours"] == pytest.approx(72 / 3600) and f["seconds_per_epoch"] == pytest.approx(36.0)
    assert (s["best_epoch"], s["epochs_run"]) == (3, 4) and np.isnan(s["train_rollout_at_best"])
    table = markdown(out)  # a run that predates a setting shows "-"
    assert "| fast | 64 | bf16 | 0.002 | 3 | 10.00 % | 1 | 0.02 | 5.00 % | 12.00 % | 36 |" in table
    assert "| slow | 16 | - | 0.001 | 4 | 9.00 % | 3 | 0.11 |  | 9.00 % | 100 |" in table


def test_curves_refuses_a_directory_without_a_checkpoint(tmp_path):
    from learn.curves import run_history
    with pytest.raises(FileNotFoundError, match="holds no last.pt or best.pt"):
        run_history(tmp_path)


def test_a_scaling_fit_recovers_the_exponent_and_extrapolates_the_median():
    """sizes: each design's error a_i N^-b_i is fitted in log-log; on synthetic reports made with b = 0.4 (per-design
    prefactors spread over a decade, exponents 0.3-0.5) the per-design median and the median's exponent come back,
    and the size at which the median reaches the target is the power law's, to round-off."""
    from learn.compare import scaling
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0.02, 0.2, 60), rng.uniform(0.3, 0.5, 60)
    sizes = [348, 548, 746]
    reports = [report({f"d{i}": a[i] * (n / 100) ** -b[i] for i in range(60)}) for n in sizes]
    result = compare(reports, ["348", "548", "746"])
    sc = scaling(result, sizes, target=0.01)
    assert sc["per_design_exponent_median"] == pytest.approx(np.median(b), rel=1e-9)
    assert 0.3 < sc["median_exponent"] < 0.5 and 0.3 < sc["p95_exponent"] < 0.5
    m = result["rows"][2]["median"]
    assert sc["median_at_target_size"] == pytest.approx(746 * (m / 0.01) ** (1 / sc["median_exponent"]))
    flat = scaling(compare([report({"d0": 0.1, "d1": 0.2})] * 2, ["a", "b"]), [100, 200], 0.01)
    assert flat["median_at_target_size"] is None  # no fall with size: the target is never reached
    with pytest.raises(ValueError, match="one per report"):
        scaling(result, [348, 746], 0.01)
    with pytest.raises(ValueError, match="at least two different"):
        scaling(result, [348, 348, 348], 0.01)


def test_cli_writes_the_scaling_section_and_plot(tmp_path):
    dirs = []
    for n in (100, 200, 400):
        d = tmp_path / f"r{n}"
        d.mkdir()
        (d / "report.json").write_text(json.dumps(report({f"d{i}": 0.05 * (i + 1) * (n / 100) ** -0.5
                                                           for i in range(5)})))
        dirs.append(str(d))
    out = tmp_path / "cmp"
    subprocess.run([sys.executable, "-m", "learn.compare", f"reports=[{','.join(dirs)}]", "sizes=[100,200,400]",
                    f"out_dir={out}"], cwd=REPO, check=True, capture_output=True)
    on_disk = json.loads((out / "compare.json").read_text())
    assert on_disk["scaling"]["median_exponent"] == pytest.approx(0.5)
    assert "error ~ N^-b" in (out / "compare.md").read_text() and (out / "scaling.png").stat().st_size > 0


def test_by_design_size_compares_within_each_bin_of_the_base_reports_sizes():
    from learn.compare import by_design_size
    sizes = {"d0": 120.0, "d1": 140.0, "d2": 210.0, "d3": 230.0}

    def sized(errors):
        r = report(errors)
        for d in r["designs"]:
            d["design_size_mm"] = sizes[d["name"]]
        return r
    base = sized({"d0": 0.02, "d1": 0.02, "d2": 0.04, "d3": 0.06})
    other = sized({"d0": 0.03, "d1": 0.03, "d2": 0.02, "d3": 0.03})  # worse when small, better when large
    out = compare([base, other], ["base", "other"])
    bins = by_design_size(out, [base, other], [0, 150, 200, 1000])
    assert [b["n"] for b in bins] == [2, 0, 2] and bins[1]["rows"] == []
    small, large = bins[0]["rows"][1], bins[2]["rows"][1]
    assert (small["better_on"], small["median_ratio"]) == (0, pytest.approx(1.5))
    assert (large["better_on"], large["median_ratio"]) == (2, pytest.approx(0.5))
    assert bins[2]["rows"][0]["median"] == pytest.approx(0.05)
    out["by_size"] = bins
    assert "| 200-1000 | 2 | other | 2.50 % | 2 of 2 | x0.500 |" in markdown(out)
    with pytest.raises(ValueError, match="size_bins"):
        by_design_size(out, [base, other], [200, 100])
    with pytest.raises(ValueError, match="design_size_mm"):
        by_design_size(out, [report({"d0": 0.1, "d1": 0.1, "d2": 0.1, "d3": 0.1}), other], [0, 1000])
