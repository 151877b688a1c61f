"""Where a learned simulator's error comes from: `.venv/bin/python -m learn.diagnose checkpoint=... [splits=...]`.

For every design of each split (conf/diagnose.yaml), per frame k = 1..F-1 and as max point error / design size:
- rollout: the model's own 10-step rollout from frame 0 (what learn.evaluate reports);
- one_step: one step from the FEA's frame k-1 (teacher forcing): how well the step itself is learned;
- motion: how far the FEA's points move in that step (the scale a one-step error compares with);
and per start frame s, the final-frame error of a rollout started from the FEA's frame s instead of frame 0
(a model trained on whole-episode rollouts only ever saw its own intermediate states; a direct model,
model.update=direct, answers every frame from frame 0, so its one_step is defined at k = 1 and its final-frame
error from frame 0 only: the other entries are NaN); plus the input floor
(learn.rollout.input_floor). And how the beams are oriented, per frame, in degrees (median over each design's beams):
chord_error, the angle between the rollout's and the FEA's chord (start section centre -> end section centre), beside
chord_rotation, the angle the FEA's chord has turned since frame 0; their ratio says how much of each beam's turn the
model gets wrong, which, times the lever arm to the far side of the grid, is most of the position error. And per
block (each joint's and beam's points, rigidly fitted onto the FEA's: learn.rigid.block_parts; median over a design's
joints and over its beams): orientation error beside the FEA block's own turn (deg), centroid placement error and the
shape error left after the fit (/ design size); and each beam's bend, its turn relative to its start joint, predicted
against the FEA's: the part of a beam's orientation error that is its own, not carried from the joints before it.
The medians go to diagnose.json / diagnose.md and one plot, split
beside split, so train vs held-out separates fitting from generalisation.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import hydra
import matplotlib
import numpy as np
import torch
from omegaconf import DictConfig

from data_schema import atomic
from learn import checkpoint, publish
from learn.checks import integer_in
from learn.dataset import GraphSet, design_paths, load_features
from learn.features import BEAM_POINTS, JOINT_POINTS, rebuild_all_points
from learn.metrics import beam_chords, fea_points, max_per_item, point_owner
from learn.model import Simulator
from learn.rigid import best_rotation, block_parts, rotation_angle_deg
from learn.rollout import input_floor, unroll

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

log = logging.getLogger(__name__)


def chords(beam_state: torch.Tensor) -> np.ndarray:
    """[..., B, S] beam states -> [..., B, 3] every beam's unit chord, start section centre -> end section centre."""
    halves = beam_chords(beam_state).numpy()
    chord = halves[..., :3] + halves[..., 3:]
    return chord / np.linalg.norm(chord, axis=-1, keepdims=True)


def angle_deg(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle between unit vectors [..., 3], degrees."""
    return np.degrees(np.arccos(np.clip((u * v).sum(-1), -1.0, 1.0)))


def median_per_item(x: np.ndarray, item: np.ndarray, n: int) -> np.ndarray:
    """[..., B] per beam -> [n, ...] the median over each item's beams."""
    return np.stack([np.median(x[..., item == i], axis=-1) for i in range(n)])


def blocks(points: np.ndarray, n_joints: int) -> tuple[np.ndarray, np.ndarray]:
    """[F, P, 3] points as rebuild_all_points orders them -> [F, J, joint points, 3] and [F, B, beam points, 3]."""
    nj, nb = len(JOINT_POINTS), len(BEAM_POINTS)
    F = points.shape[0]
    return (points[:, :n_joints * nj].reshape(F, n_joints, nj, 3),
            points[:, n_joints * nj:].reshape(F, -1, nb, 3))


def block_split(rollout: np.ndarray, truth: np.ndarray, data: GraphSet, size: np.ndarray) -> dict:
    """Per frame k >= 1, the rollout's blocks (each joint's and beam's points) against the FEA's, split into
    orientation error (deg) beside the FEA block's turn since frame 0, placement (centroid distance / design size) and
    shape (what is left after a rigid fit, / design size): learn.rigid.block_parts; median over each design's joints
    and over its beams -> [n, F-1] per key."""
    n, J = len(data), data.joint_offsets[-1]
    item = {"joint": np.repeat(np.arange(n), np.diff(data.joint_offsets)),
            "beam": np.repeat(np.arange(n), np.diff(data.beam_offsets))}
    out = {}
    for kind, pred, fea in zip(("joint", "beam"), blocks(rollout, J), blocks(truth, J)):
        parts = block_parts(pred[1:], fea[1:], fea[:1])
        for key, x in parts.items():
            med = median_per_item(x, item[kind], n)
            out[f"{kind}_{key}"] = med if key.endswith("deg") else med / size[:, None]
    start = data.static.index.beam_starts().numpy()
    bend_error, bend = relative_turns(blocks(rollout, J), blocks(truth, J), start)
    out["beam_bend_error_deg"] = median_per_item(bend_error, item["beam"], n)
    out["beam_bend_deg"] = median_per_item(bend, item["beam"], n)
    return out


def relative_turns(predicted: tuple[np.ndarray, np.ndarray], truth: tuple[np.ndarray, np.ndarray],
                   start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each beam's turn relative to its start joint, from block points ([F, J, nj, 3], [F, B, nb, 3]) and the
    beams' start joints [B] -> [F-1, B] twice: the angle between the predicted and the FEA's relative rotation
    (the beam's own bend, apart from how its joint is turned: the local part of the orientation error, against
    the absolute one the rigid fit reports) and the FEA's relative turn since frame 0 (deg)."""
    def turns(joints, beams, ref_joints, ref_beams):  # block rotations from frame 0 -> beam relative to its joint
        Rj = best_rotation(ref_joints[None], joints[1:])  # [F-1, J, 3, 3]
        Rb = best_rotation(ref_beams[None], beams[1:])
        return np.swapaxes(Rj[:, start], -1, -2) @ Rb  # in the joint's own frame: R_joint^T R_beam
    ref = truth[0][0], truth[1][0]
    rel_pred, rel_true = turns(*predicted, *ref), turns(*truth, *ref)
    return (rotation_angle_deg(rel_pred @ np.swapaxes(rel_true, -1, -2)),
            rotation_angle_deg(rel_true))


def diagnose_set(model: Simulator, data: GraphSet) -> dict:
    """Per design [n, ...] arrays of max error / design size (see the module doc)."""
    size = np.array([f.design_size for f in data.items])
    owner, n, F = point_owner(data), len(data), len(data.t)
    truth = fea_points(data)  # [F, P, 3]
    with torch.inference_mode():
        js, bs = unroll(model, data.joint_state[0], data.beam_state[0], data.static, data.t)
        rollout = rebuild_all_points(js, bs).numpy()
        rollout_chords = chords(bs[1:])
        if model.direct:  # every frame from the design (frame 0): no step starts from a later FEA frame
            one_step = np.full_like(rollout[1:], np.nan)
            one_step[0] = rollout[1]
            from_start = [rollout[-1]] + [np.full_like(rollout[-1], np.nan)] * (F - 2)
        else:
            j1, b1 = model.step(data.joint_state[:-1], data.beam_state[:-1], data.static, data.t[:-1])
            one_step = rebuild_all_points(j1, b1).numpy()  # [F-1, P, 3]: frame k from the FEA's frame k-1
            from_start = []
            for s in range(F - 1):
                js, bs = unroll(model, data.joint_state[s], data.beam_state[s], data.static, data.t[s:])
                from_start.append(rebuild_all_points(js[-1], bs[-1]).numpy())
    dist = lambda a, b: np.linalg.norm(a - b, axis=-1)  # noqa: E731
    rel = lambda e: (max_per_item(e, owner, n) / size).T  # noqa: E731  [n, ...]
    beam_item = np.repeat(np.arange(n), np.diff(data.beam_offsets))
    fea_chords = chords(data.beam_state)  # [F, B, 3]
    return {"rollout": rel(dist(rollout[1:], truth[1:])), "one_step": rel(dist(one_step, truth[1:])),
            "motion": rel(dist(truth[1:], truth[:-1])),
            "final_from_start": rel(dist(np.stack(from_start), truth[-1][None])),
            "chord_error_deg": median_per_item(angle_deg(rollout_chords, fea_chords[1:]), beam_item, n),
            "chord_rotation_deg": median_per_item(angle_deg(fea_chords[1:], fea_chords[:1]), beam_item, n),
            **block_split(rollout, truth, data, size),
            "input_floor": np.array([input_floor(model, f).max() / f.design_size for f in data.items])}


def medians(d: dict) -> dict:
    """Median over designs of every entry; an entry a model does not define (NaN: a direct model's steps from later
    FEA frames) is None, so the JSON stays standard."""
    plain = lambda x: None if isinstance(x, float) and np.isnan(x) else x  # noqa: E731
    out = {}
    for k, v in d.items():
        m = np.median(v, axis=0).tolist()
        out[k] = [plain(x) for x in m] if isinstance(m, list) else plain(m)
    return out


def markdown(report: dict) -> str:
    pct = lambda xs: " | ".join("-" if x is None else f"{100 * x:.2f}" for x in xs)  # noqa: E731
    deg = lambda xs: " | ".join(f"{x:.2f}" for x in xs)  # noqa: E731
    lines = [f"# Error sources of {report['checkpoint']}", "",
             "Median over each split's designs of max point error / design size (%), per frame k; beam chords: the "
             "median over designs of each design's median over its beams (degrees).", ""]
    for split, m in report["splits"].items():
        F = len(m["rollout"])
        lines += [f"## {split} ({m['n_designs']} designs)", "",
                  "| | " + " | ".join(f"k={k}" for k in range(1, F + 1)) + " |", "|---" * (F + 1) + "|",
                  f"| rollout from frame 0 | {pct(m['rollout'])} |",
                  f"| one step from FEA frame k-1 | {pct(m['one_step'])} |",
                  f"| FEA motion in step k | {pct(m['motion'])} |",
                  f"| final error, rollout from FEA frame k-1 | {pct(m['final_from_start'])} |",
                  f"| beam chord direction error (deg) | {deg(m['chord_error_deg'])} |",
                  f"| FEA beam chord rotation since frame 0 (deg) | {deg(m['chord_rotation_deg'])} |",
                  *(row for kind in ("joint", "beam") for row in (
                      f"| {kind}s: orientation error, rigid fit (deg) | {deg(m[f'{kind}_orientation_error_deg'])} |",
                      f"| {kind}s: FEA turn since frame 0 (deg) | {deg(m[f'{kind}_turn_deg'])} |",
                      f"| {kind}s: centroid placement error | {pct(m[f'{kind}_placement'])} |",
                      f"| {kind}s: shape error after the rigid fit | {pct(m[f'{kind}_shape'])} |")),
                  f"| beams: bend error, turn relative to the start joint (deg) | {deg(m['beam_bend_error_deg'])} |",
                  f"| beams: FEA bend, turn relative to the start joint (deg) | {deg(m['beam_bend_deg'])} |", "",
                  f"input floor (PCA'd geometry): median {100 * m['input_floor']:.3f} %", ""]
    return "\n".join(lines)


def plot(report: dict, path: Path) -> None:
    splits = report["splits"]
    fig, axes = plt.subplots(2, len(splits), figsize=(5.5 * len(splits), 7.5), squeeze=False, sharey="row")
    for ax, (split, m) in zip(axes[1], splits.items()):
        k = np.arange(1, len(m["chord_error_deg"]) + 1)
        ax.plot(k, m["chord_error_deg"], "o-", label="beam chord direction error")
        ax.plot(k, m["chord_rotation_deg"], "^:", label="FEA beam chord rotation since frame 0")
        ax.plot(k, m["joint_orientation_error_deg"], "s-", label="joint orientation error (rigid fit)")
        ax.plot(k, m["joint_turn_deg"], "v:", label="FEA joint turn since frame 0")
        ax.set_xlabel("frame k")
        ax.grid(alpha=0.3)
    axes[1][0].set_ylabel("degrees (median over beams, then designs)")
    axes[1][0].legend(fontsize=8)
    for ax, (split, m) in zip(axes[0], splits.items()):
        k = np.arange(1, len(m["rollout"]) + 1)
        for key, style, label in (("rollout", "o-", "rollout from frame 0"),
                                  ("one_step", "s--", "one step from FEA frame k-1"),
                                  ("motion", "^:", "FEA motion in step k"),
                                  ("final_from_start", "d-.", "final error, start at FEA frame k-1")):
            ax.plot(k, 100 * np.asarray(m[key], dtype=float), style, label=label)  # None (not defined): a gap
        ax.set_title(f"{split}: {m['n_designs']} designs (medians)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("max error / design size (%)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def diagnose(cfg: DictConfig) -> dict:
    torch.set_num_threads(integer_in(cfg.threads, "threads", 1, 1024, "torch threads"))
    ckpt = checkpoint.load(publish.one_checkpoint(cfg.checkpoint, "checkpoint"))  # or a published models/<name>
    model = checkpoint.model_from(ckpt)
    data_dir = Path(cfg.data_dir or ckpt["config"]["data_dir"])
    unknown = [s for s in cfg.splits if s not in ckpt["split"]]
    if unknown:
        raise ValueError(f"splits={list(cfg.splits)}: {unknown} not in {cfg.checkpoint}; "
                         f"allowed {sorted(ckpt['split'])}")
    report = {"checkpoint": str(cfg.checkpoint), "data_dir": str(data_dir), "splits": {}}
    for split in cfg.splits:
        names = sorted(ckpt["split"][split])[: int(cfg.max_designs)] if cfg.max_designs else ckpt["split"][split]
        if not names:
            continue
        data = GraphSet.build(load_features(design_paths(names, data_dir, ckpt["config"])))
        report["splits"][split] = {"n_designs": len(names), **medians(diagnose_set(model, data))}
        log.info("%s: %d designs, final rollout error median %.2f %%", split, len(names),
                 100 * report["splits"][split]["rollout"][-1])
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic.write_text(out / "diagnose.json", json.dumps(report, indent=1))
    atomic.write_text(out / "diagnose.md", markdown(report))
    plot(report, out / "diagnose.png")
    return report


@hydra.main(version_base="1.3", config_path="../conf", config_name="diagnose")
def main(cfg: DictConfig) -> None:
    diagnose(cfg)


if __name__ == "__main__":
    main()
