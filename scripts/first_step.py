"""How well can a model shape fit the first steps of an episode? A short training on the first `--frames` frames.

The step from the flat, stress-free design to the first frame (10 % of the load) is a global static problem: the
network sees only the geometry and the actuator kinds, and every block's motion depends on the whole grid. This
script trains a fresh simulator (model and optimiser from conf/, any `key=value` override as for `learn.train`) on
the first `--frames` frames of `--train-designs` training designs (x rotations x mirror; the held-out designs are
those of `--split-from`, a split file or a checkpoint) and reports, every `--log-every` epochs, the median over
training and validation designs of the max point error / design size at the last of those frames, beside the FEA's
own motion there. The learning rate follows conf/optim's schedule over `--epochs` (step: x0.1 from half of them
on, `optim.lr_drop_at`), as learn.train's does. A quick probe (minutes on one core) of
what limits a model shape or a loss before a full training (hours); one row per run is appended to `--out`/first_step.csv.
Session 42's probe of the first step as memorised (26 designs as sampled, batch 2, `optim.lr=3e-4`, fp32):

    .venv/bin/python scripts/first_step.py --train-designs 26 --epochs 301 rotations=1 lattice_turns=1 mirror=false \
        batch_size=2 optim.lr=3e-4 precision=fp32 threads=1 [option=...]

    .venv/bin/python scripts/first_step.py --epochs 61 model.n_blocks=4 model.latent=48 'model.widths=[96,48]'
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402

from learn import checkpoint  # noqa: E402
from learn.dataset import GraphSet, episode_paths, extend_split, load_features  # noqa: E402
from learn.features import EpisodeFeatures  # noqa: E402
from learn.metrics import rollout_errors  # noqa: E402
from learn.model import Simulator  # noqa: E402
from learn.train import augmented, append_result, model_args, retention_of, train_epoch  # noqa: E402


def first_frames(f: EpisodeFeatures, frames: int) -> EpisodeFeatures:
    return dataclasses.replace(f, t=f.t[:frames], joint_state=f.joint_state[:frames],
                               beam_state=f.beam_state[:frames], fea_points=f.fea_points[:frames])


def median_final_error(model: Simulator, data: GraphSet) -> float:
    model.eval()
    err = float(np.median(rollout_errors(model, data)[0][:, -1]))
    model.train()
    return err


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("overrides", nargs="*", help="conf/train.yaml overrides, e.g. model.n_blocks=4")
    p.add_argument("--data-dir", default="data/ds_default")
    p.add_argument("--split-from", default="conf/held_out/ds_default.yaml",
                   help="split file or checkpoint whose held-out designs are kept (the rest of --data-dir is train)")
    p.add_argument("--train-designs", type=int, default=120)
    p.add_argument("--frames", type=int, default=2, help="frames kept from each episode (2 = the first step)")
    p.add_argument("--epochs", type=int, default=61)
    p.add_argument("--log-every", type=int, default=20)
    p.add_argument("--out", default="reports/first_step")
    args = p.parse_args()
    if args.frames < 2:
        raise SystemExit(f"--frames={args.frames}: must be >= 2 (frame 0 and at least one step)")
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose("train", overrides=[*args.overrides, f"epochs={args.epochs}"])
    torch.set_num_threads(int(cfg.threads) or 1)
    torch.manual_seed(int(cfg.seed))

    try:
        split = extend_split(checkpoint.split_of(args.split_from), (p.name for p in episode_paths(args.data_dir)))
    except FileNotFoundError as e:
        raise SystemExit(f"--data-dir {args.data_dir}, --split-from {args.split_from}: {e}")
    names = {"train": split["train"][:args.train_designs], "val": split["val"]}
    def load(part: str) -> list[EpisodeFeatures]:
        return [first_frames(f, args.frames) for f in load_features([Path(args.data_dir) / n for n in names[part]])]

    train, val = load("train"), load("val")
    train_set = GraphSet.build(augmented(train, cfg))
    train_probe, val_set = GraphSet.build(train[:40]), GraphSet.build(val)
    model = Simulator.fit(model_args(cfg.model), train_set.joint_state, train_set.beam_state, train_set.static,
                          retention_of(cfg), cfg.delta_std_floor)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.optim.lr, weight_decay=cfg.optim.weight_decay)
    motion = float(np.median([np.linalg.norm(f.fea_points[-1] - f.fea_points[0], axis=-1).max() / f.design_size
                              for f in val]))
    print(f"{len(train)} training designs (x{len(train_set) // len(train)} augmented), {len(val)} validation, "
          f"frames 0..{args.frames - 1}; {model.n_parameters} parameters; FEA max motion by the last frame "
          f"(validation median) {100 * motion:.2f} %", flush=True)

    t0 = time.perf_counter()
    for epoch in range(args.epochs):
        train_epoch(model, opt, train_set, cfg, epoch)
        if epoch % args.log_every == 0 or epoch == args.epochs - 1:
            train_err, val_err = median_final_error(model, train_probe), median_final_error(model, val_set)
            print(f"epoch {epoch:4d}  train {100 * train_err:5.2f} %  val {100 * val_err:5.2f} %  "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)

    row = {"overrides": " ".join(args.overrides), "train_designs": len(train), "frames": args.frames,
           "epochs": args.epochs, "parameters": model.n_parameters, "fea_motion_val": round(motion, 5),
           "train_error": round(train_err, 5), "val_error": round(val_err, 5),
           "seconds": round(time.perf_counter() - t0, 1)}
    out = Path(args.out) / "first_step.csv"
    append_result(out, row)
    print(f"-> {out}")


if __name__ == "__main__":
    main()
