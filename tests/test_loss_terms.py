"""scripts/loss_terms.py: the loss split into its terms adds back up to the loss a `loss_geometry=both` run descends."""
from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from learn import checkpoint
from learn.dataset import GraphSet, load_features
from learn.metrics import multistep_loss
from test_learn_train import data_dir, trained  # noqa: F401  (module fixtures: tiny episodes, a model)

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = [sys.executable, str(ROOT / "scripts" / "loss_terms.py")]


def test_the_terms_add_up_to_the_both_loss_and_bad_input_is_refused(trained, data_dir, tmp_path):  # noqa: F811
    run_dir, _ = trained
    out = tmp_path / "terms.csv"
    r = subprocess.run(SCRIPT + [str(run_dir / "last.pt"), "--data-dir", str(data_dir), "--designs", "2",
                                 "--out", str(out)], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    row = next(csv.DictReader(out.open()))
    value = {t: float(row[f"{t}_value"]) for t in ("geometry_columns", "stress_columns", "points")}
    assert all(v > 0 for v in value.values()) and all(float(row[f"{t}_grad_norm"]) > 0 for t in value)
    assert -1 <= float(row["cos_geometry_points"]) <= 1

    ckpt = checkpoint.load(run_dir / "last.pt")
    model = checkpoint.model_from(ckpt).train()
    batch = GraphSet.build(load_features([data_dir / n for n in ckpt["split"]["train"][:2]]))
    stress_weight = float(ckpt["config"]["stress_weight"])
    with torch.no_grad():
        both = float(multistep_loss(model, batch, int(ckpt["config"]["rollout_horizon"]), stress_weight=stress_weight,
                                    geometry="both", point_weight=0.3))
    parts = value["geometry_columns"] + value["stress_columns"] + 0.3 * value["points"]
    assert parts == pytest.approx(both, rel=1e-4)  # the CSV rounds to 6 digits

    bad = subprocess.run(SCRIPT + [str(run_dir / "last.pt"), "--designs", "0"], capture_output=True, text=True,
                         timeout=600, cwd=ROOT)
    assert bad.returncode != 0 and "--designs=0" in bad.stderr
    bad = subprocess.run(SCRIPT + [str(run_dir / "last.pt"), "--data-dir", str(tmp_path)], capture_output=True,
                         text=True, timeout=600, cwd=ROOT)
    assert bad.returncode != 0 and "training designs not in --data-dir" in bad.stderr
