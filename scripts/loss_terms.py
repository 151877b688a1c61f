"""How large each term of the training loss is for trained models, and how hard each one pulls on the weights.

For every checkpoint, over its first `--designs` training designs (the split stored in it, as trained: whole episodes
from frame 0 at its `rollout_horizon`, no noise), the three terms learn.metrics.multistep_loss can weigh:
- geometry columns: every geometry column of the state in units of its step std (`loss_geometry=columns`);
- stress columns: the stress columns likewise, at the run's `stress_weight`;
- points: the rebuilt points' distance to the FEA's in units of the mean geometry step std, at weight 1
  (`loss_geometry=points`; `both` adds it to the columns at `point_weight`);
each as its value and as the norm of its gradient on the weights (Adam scales the sum's gradient as a whole, so the
ratio of the norms is how much of each step a term decides). One row per checkpoint to `--out` (CSV) and a table on
stdout. Session 43: why `loss_geometry=both` at point_weight 1 trained as `points` does.

    .venv/bin/python scripts/loss_terms.py runs/a/best.pt [runs/b/best.pt ...] [--data-dir data/ds_default]
        [--designs 16] [--out reports/loss_terms.csv]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
import torch  # noqa: E402

from learn import checkpoint  # noqa: E402
from learn.dataset import GraphSet, load_features  # noqa: E402
from learn.metrics import multistep_loss  # noqa: E402
from learn.train import append_result  # noqa: E402


def value_and_gradient(model, batch: GraphSet, horizon: int, **terms) -> tuple[float, torch.Tensor]:
    model.zero_grad()
    loss = multistep_loss(model, batch, horizon, **terms)
    loss.backward()
    grad = torch.cat([(torch.zeros_like(p) if p.grad is None else p.grad).flatten()  # a weight the term never
                      for p in model.parameters()])  # reaches: zeros, so every term's gradient lines up
    return float(loss.detach()), grad


def term_sizes(path: str, data_dir: str, designs: int) -> dict:
    ckpt = checkpoint.load(path)
    model, cfg = checkpoint.model_from(ckpt).train(), ckpt["config"]  # the run's own horizon and stress weight,
    horizon, stress_weight = int(cfg["rollout_horizon"]), float(cfg["stress_weight"])  # not conf/'s literals again
    names = ckpt["split"]["train"][:designs]
    if not names:
        raise SystemExit(f"{path}: its split holds no training designs")
    missing = [n for n in names if not (Path(data_dir) / n).exists()]
    if missing:
        raise SystemExit(f"{path}: training designs not in --data-dir {data_dir}: {missing[:3]}")
    batch = GraphSet.build(load_features([Path(data_dir) / n for n in names]))
    geometry = value_and_gradient(model, batch, horizon, geometry="columns", stress_weight=0.0)
    columns = value_and_gradient(model, batch, horizon, geometry="columns", stress_weight=stress_weight)
    points = value_and_gradient(model, batch, horizon, geometry="points", stress_weight=0.0)
    stress = (columns[0] - geometry[0], columns[1] - geometry[1])
    row = {"checkpoint": path, "designs": len(names), "horizon": horizon, "stress_weight": stress_weight,
           "loss_geometry": cfg.get("loss_geometry", "columns"), "point_weight": cfg.get("point_weight", "")}
    for name, (value, grad) in (("geometry_columns", geometry), ("stress_columns", stress), ("points", points)):
        row[f"{name}_value"], row[f"{name}_grad_norm"] = round(value, 6), round(float(grad.norm()), 6)
    cosine = torch.nn.functional.cosine_similarity(geometry[1], points[1], dim=0)
    row["cos_geometry_points"] = round(float(cosine), 4)  # do the two geometry terms pull the same way?
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="+")
    p.add_argument("--data-dir", default="data/ds_default")
    p.add_argument("--designs", type=int, default=16, help="the checkpoint's first N training designs, one batch")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", help="append one CSV row per checkpoint here")
    a = p.parse_args()
    if a.designs < 1:
        raise SystemExit(f"--designs={a.designs}: must be >= 1")
    torch.set_num_threads(a.threads)
    print("| checkpoint | loss_geometry | geometry columns: value, grad norm | stress columns | points | "
          "cos(grad geometry, grad points) |\n|---|---|---|---|---|---|")
    for path in a.checkpoints:
        r = term_sizes(path, a.data_dir, a.designs)
        cells = [f"{r[f'{n}_value']:.4g}, {r[f'{n}_grad_norm']:.4g}" for n in ("geometry_columns", "stress_columns",
                                                                               "points")]
        print(f"| {path} | {r['loss_geometry']} {r['point_weight']} | {' | '.join(cells)} | "
              f"{r['cos_geometry_points']:.3f} |", flush=True)
        if a.out:
            append_result(a.out, r)


if __name__ == "__main__":
    main()
