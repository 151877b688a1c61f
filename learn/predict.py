"""Predict a design's morph with a trained simulator: `.venv/bin/python -m learn.predict` (conf/predict.yaml).

The input is an episode whose frame 0 is the design before triggering: a one-frame episode from
`python -m fea_factory.initial design=...` (no solve; `make predict DESIGN=...` runs both) or any solved episode,
whose later frames are then the FEA reference the prediction is compared with; or several such episodes (a list,
or a directory of them), rolled out together in one pass, each design's outputs in out_dir/<episode stem>/ with
out_dir/predictions.csv (one row per design: verdict, error). Writes into out_dir:
- prediction.view.xdmf (+ .view.h5): the predicted shape per frame as a coarse hex mesh (one hexahedron per joint,
  two per beam, learn.shapes), displacement from frame 0 (ParaView: Warp By Vector) and, with an FEA reference,
  its displacement and the point error (mm);
- prediction.json: the validity verdict (a flagged rollout is not an answer), the wall time of the rollout and,
  with a reference, max / mean error over frames as a fraction of the design size;
- prediction.png: the final shape (and the FEA's).
"""
from __future__ import annotations

import json
import logging
import textwrap
import time
from pathlib import Path

import hydra
import matplotlib
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from data_schema import atomic
from data_schema.episode import read_episode
from data_schema.view import write_series
from learn import ensemble
from learn.checks import integer_in
from learn.features import extract
from learn.plots import equal_axes
from learn.rollout import Rollout, rollout_many
from learn.shapes import block_hexahedra
from learn.validity import check, thresholds

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

log = logging.getLogger(__name__)


def has_reference(r: Rollout) -> bool:
    """True when the source episode holds FEA frames at the rollout's times."""
    f = r.features
    return f.n_frames == r.n_frames and np.allclose(f.t, r.t)


def write_view(r: Rollout, path: Path) -> Path:
    cells, block = block_hexahedra(r.features.incidence.n_joints, r.features.incidence.n_beams)
    points = r.points
    point_data = {"displacement": points - points[0]}
    if has_reference(r):
        fea = r.features.fea_points + r.origin
        point_data.update(fea_displacement=fea - points[0], error_mm=np.linalg.norm(points - fea, axis=-1))
    return write_series(path, points[0], cells, r.t, point_data=point_data, static_cell_data={"block": block})


HEX_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7))


def plot_prediction(r: Rollout, title: str, path: Path) -> None:
    """Final frame as hex wireframes: the prediction (red), the FEA when the episode has it (blue), the design."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    cells, _ = block_hexahedra(r.features.incidence.n_joints, r.features.incidence.n_beams)
    edges = np.asarray(HEX_EDGES)
    segments = lambda pts: pts[cells[:, edges]].reshape(-1, 2, 3)  # noqa: E731
    shapes = [(r.points[0], "0.75", "design (t = 0)"), (r.points[-1], "tab:red", "learned")]
    if has_reference(r):
        shapes.insert(1, (r.features.fea_points[-1] + r.origin, "tab:blue", "FEA"))
    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    for pts, color, label in shapes:
        ax.add_collection3d(Line3DCollection(segments(pts), colors=color, linewidths=0.6, label=label))
    equal_axes(ax, r.points)
    ax.set_title("\n".join(textwrap.wrap(title, 70)), fontsize=9)
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def episode_paths(value) -> list[Path]:
    """conf episode: one file, a list of files, or a directory (its *.h5, sorted by name)."""
    items = [value] if isinstance(value, (str, Path)) else list(value)
    paths: list[Path] = []
    for item in items:
        path = Path(str(item))
        paths += sorted(path.glob("*.h5")) if path.is_dir() else [path]
    if not paths:
        raise ValueError(f"episode={value!r}: no episode files (give a .h5 file, a list of them, or a directory "
                         "holding some)")
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"episode: {missing[:5]} not found")
    return paths


def answer(cfg: DictConfig, model, ckpt: dict, raw: Rollout, episode: Path, out_dir: Path, timing: dict) -> dict:
    """One design's outputs in out_dir (view, verdict and error, png) as predict writes them; -> its result."""
    f = raw.features
    limits = thresholds(OmegaConf.to_container(cfg.validity), model)  # those of the model's frame
    verdict = check(model, raw, **limits, envelope=ckpt.get("envelope"))
    weld = bool(cfg.get("weld", True))
    r = raw.welded() if weld else raw  # the answer written and measured; the check read the blocks as predicted
    out_dir.mkdir(parents=True, exist_ok=True)
    sources = ensemble.checkpoint_paths(cfg.checkpoint)
    result = {
        "episode": str(episode), "checkpoint": sources[0] if len(sources) == 1 else sources, "steps": int(cfg.steps),
        "t": r.t.tolist(), "design_size_mm": f.design_size, "valid": verdict.valid, "validity": verdict.as_dict(),
        **timing, "threads": int(cfg.threads), "welded": weld,
        "view": str(write_view(r, out_dir / "prediction.view.xdmf")),
    }
    if has_reference(r):
        err = np.linalg.norm(r.local_points - f.fea_points, axis=-1)  # [F, P] mm
        result.update(max_rel_error=float(err.max() / f.design_size), mean_rel_error=float(err.mean() / f.design_size),
                      max_rel_error_per_frame=(err.max(axis=1) / f.design_size).tolist(), reference="FEA frames of "
                      "the input episode")
    verdict_text = "valid" if verdict.valid else "FLAGGED: " + "; ".join(verdict.reasons)
    err_text = f", max error {100 * result['max_rel_error']:.2f} % of {f.design_size:.0f} mm" \
        if "max_rel_error" in result else ""
    if cfg.plots:
        plot_prediction(r, f"{episode.name}: {cfg.steps} steps{err_text}; {verdict_text}", out_dir / "prediction.png")
    atomic.write_text(out_dir / "prediction.json", json.dumps(result, indent=1))
    log.info("%s: %d steps%s; %s -> %s", episode.name, cfg.steps, err_text, verdict_text, out_dir)
    return result


def predict(cfg: DictConfig) -> dict | list[dict]:
    """One episode: its result (out_dir/prediction.*). Several (a list or a directory): all rolled out in one pass
    (learn.rollout.rollout_many), each design's outputs in out_dir/<episode stem>/, and out_dir/predictions.csv and
    predictions.json with a row per design; -> the list of results."""
    torch.set_num_threads(integer_in(cfg.threads, "threads", 1, 1024, "torch threads while rolling out and timing"))
    steps = integer_in(cfg.steps, "steps", 1, 1000, "rollout steps; the training episodes have 10")
    episodes = episode_paths(cfg.episode)
    model, ckpt = ensemble.load(ensemble.checkpoint_paths(cfg.checkpoint))
    model.answer_with(cfg.rollout_rotations, cfg.rollout_mirror, cfg.rollout_lattice_turns)
    features = [extract(read_episode(e), name=e.name) for e in episodes]
    start = time.perf_counter()
    raws = rollout_many(model, features, steps=steps)
    wall_ms = 1e3 * (time.perf_counter() - start)
    out_dir = Path(cfg.out_dir)
    if len(episodes) == 1 and isinstance(cfg.episode, str) and not Path(cfg.episode).is_dir():
        timing = {"rollout_ms": wall_ms, "timing": "rollout_ms: one eager rollout (initial graph -> rebuilt points of "
                  "every frame), first call; learn.evaluate measures the compiled steady state"}
        return answer(cfg, model, ckpt, raws[0], episodes[0], out_dir, timing)
    timing = {"rollout_ms": wall_ms / len(episodes), "batch": len(episodes), "batch_rollout_ms": wall_ms,
              "timing": f"rollout_ms: one eager rollout of all {len(episodes)} designs at once (learn.rollout."
                        "rollout_many), first call, over the count; scripts/bench_rollout.py --batch measures the "
                        "compiled steady state"}
    stems = [e.stem for e in episodes]
    if len(set(stems)) < len(stems):
        raise ValueError("episode: two files share a name; their outputs would share a directory")
    results = [answer(cfg, model, ckpt, r, e, out_dir / e.stem, timing) for r, e in zip(raws, episodes)]
    columns = ["episode", "valid", "max_rel_error", "mean_rel_error", "design_size_mm", "view"]
    rows = [{c: r.get(c, "") for c in columns} for r in results]
    atomic.write_csv(out_dir / "predictions.csv", rows, columns)
    atomic.write_text(out_dir / "predictions.json", json.dumps({**timing, "designs": results}, indent=1))
    log.info("%d designs in one pass: %.1f ms (%.2f ms per design), %d flagged -> %s", len(episodes), wall_ms,
             wall_ms / len(episodes), sum(not r["valid"] for r in results), out_dir)
    return results


@hydra.main(version_base="1.3", config_path="../conf", config_name="predict")
def main(cfg: DictConfig) -> None:
    predict(cfg)


if __name__ == "__main__":
    main()
