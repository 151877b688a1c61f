"""scripts/error_breakdown.py: counts by actuator kind, the size table and the two validity rules, from reports."""
import json
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent


def design(kind, size, err, oor=0.0, unrolled=None):
    return {"actuators": kind, "design_size_mm": size, "max_rel_error": err,
            "validity": {"out_of_range_fraction": oor,
                         "unrolled_one_kind": (0.0 if kind == "mixed" else 0.5) if unrolled is None else unrolled}}


def test_the_breakdown_counts_bad_answers_by_kind_and_the_rules_that_flag_them(tmp_path):
    a = [design("mixed", 140, 0.01), design("mixed", 210, 0.12, oor=0.5), design("all down", 180, 0.30),
         design("all up", 160, 0.02, unrolled=0.95)]
    b = [design("mixed", 220, 0.03), design("all down", 200, 0.02)]
    for name, ds in (("a", a), ("b", b)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "report.json").write_text(json.dumps({"designs": ds}))
    out = tmp_path / "bd.md"
    subprocess.run([sys.executable, "scripts/error_breakdown.py", str(tmp_path / "a"), str(tmp_path / "b"),
                    "--out", str(out), "--max-out-of-range", "0.381"], cwd=REPO, check=True, capture_output=True)
    text = out.read_text()
    assert "| pooled | all down | 2 | 1 |" in text and "| pooled | mixed | 3 | 1 |" in text
    assert "| 200-225 | - | 1 | 12.00 % | 12.00 % |" in text  # report a's mixed designs only
    # 0.867: the out-of-range design and the unrolled all-up one; the all-down 0.30 passes
    assert "| out of range > 0.381 or unrolled > 0.867 | 1 of 2 | 1 of 4 | 0.25 |" in text
    assert "| out of range > 0.381 or unrolled > 0 | 2 of 2 | 2 of 4 | 0.50 |" in text  # every one-kind design
    # by default the fixed rule is conf/validity's (the local section's), not a copy of it
    local = yaml.safe_load((REPO / "conf" / "validity" / "default.yaml").read_text())["local"]
    subprocess.run([sys.executable, "scripts/error_breakdown.py", str(tmp_path / "a"), "--out", str(out)], cwd=REPO,
                   check=True, capture_output=True)
    assert f"| out of range > {local['max_out_of_range']:g} or unrolled > 0 |" in out.read_text()
    bad = subprocess.run([sys.executable, "scripts/error_breakdown.py", str(tmp_path / "a"), "--bins", "200,100"],
                         cwd=REPO, capture_output=True, text=True)
    assert bad.returncode != 0 and "--bins=200,100" in bad.stderr


def test_per_model_thresholds_come_from_the_models_own_validation_designs_and_are_measured_on_the_rest(tmp_path):
    split = tmp_path / "split.yaml"
    split.write_text("val: [v1.h5, v2.h5, v3.h5]\ntest: []\n")
    val = [dict(design("mixed", 150, 0.01, oor=x), name=f"v{i}.h5") for i, x in enumerate((0.1, 0.2, 0.3), 1)]
    rest = [dict(design("mixed", 150, 0.12, oor=0.25), name="a.h5"),   # bad: above q0.5 (0.2), below the fixed 0.381
            dict(design("mixed", 150, 0.02, oor=0.15), name="b.h5"),   # good, below both
            dict(design("all up", 150, 0.02, oor=0.0), name="c.h5")]   # good, one-kind: flagged by either
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "report.json").write_text(json.dumps({"designs": val + rest}))
    out = tmp_path / "bd.md"
    subprocess.run([sys.executable, "scripts/error_breakdown.py", str(tmp_path / "m"), "--split", str(split),
                    "--quantiles", "0.5", "--out", str(out), "--max-out-of-range", "0.381"],
                   cwd=REPO, check=True, capture_output=True)
    text = out.read_text()
    assert f"| {tmp_path / 'm'} | fixed | 0.381 | 0 of 1 | 1 of 2 | -0.50 |" in text  # validation designs not counted
    assert f"| {tmp_path / 'm'} | validation q0.5 | 0.200 | 1 of 1 | 1 of 2 | 0.50 |" in text
    bad = subprocess.run([sys.executable, "scripts/error_breakdown.py", str(tmp_path / "m"), "--quantiles", "1.5"],
                         cwd=REPO, capture_output=True, text=True)
    assert bad.returncode != 0 and "--quantiles=1.5" in bad.stderr
    for option, value in (("--quantiles", "0.5,x"), ("--bins", "0,a")):
        bad = subprocess.run([sys.executable, "scripts/error_breakdown.py", str(tmp_path / "m"), option, value],
                             cwd=REPO, capture_output=True, text=True)
        assert bad.returncode != 0 and f"{option}={value}: give numbers" in bad.stderr
