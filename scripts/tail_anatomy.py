"""What the worst held-out answers get wrong, measured on their rollouts: `.venv/bin/python scripts/tail_anatomy.py
--checkpoint models/record_s0_ft2,models/record_s1_ft2 --report reports/ft2_pair [--worst 22] [--out F.md]`.

--report is a `make reference-evaluate` directory (its 52/ and fresh/ reports name the designs and where they live);
the designs are ranked by that report's max error and the --worst of them set apart from the rest. Per design, at the
final frame (the one the max over frames mostly is):
- shape: the max point error left once the whole answer is moved rigidly onto the FEA's (learn.rigid.shape_error), so
  error - shape is what a tilt or shift of the whole answer carries;
- amplitude: the factor a minimising |x0 + a (answer - x0) - FEA| over the points (x0 the flat design): a < 1 says the
  answer curls too little, a > 1 too much;
- hang: the answer's vertical error minus the FEA's, weighted by each point's distance from the fixed joint, / design
  size (< 0: the answer hangs lower);
- pinned joint: the max error once the answer is turned by the FEA fixed joint's own turn since frame 0 about its
  clamped top-face centre (the model holds the fixed joint still, pin_fixed_joint; the FEA clamps only that face): what
  letting it turn could give at most, if the network did not already carry that turn in its beams;
- from frame s: the final-frame error of a rollout started from the FEA's frame s (the first checkpoint alone, learn.
  rollout.unroll), s in --starts: whether the last steps from the right state fail, or the path to them.
Session 65 (docs/learned_simulator.md) measured the ft2 pair's tail with this.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from data_schema import atomic  # noqa: E402
from learn import ensemble  # noqa: E402
from learn.dataset import load_features  # noqa: E402
from learn.diagnose import blocks  # noqa: E402
from learn.features import JOINT_POINTS, rebuild_all_points  # noqa: E402
from learn.graph import JOINT  # noqa: E402
from learn.model import static_from  # noqa: E402
from learn.rigid import best_rotation, shape_error  # noqa: E402
from learn.rollout import rollout, unroll  # noqa: E402

SOURCES = {"52": "data/ds_default", "fresh": "data/ds_heldout"}  # make reference-evaluate's parts and their data
TOP_CENTER = [name for name, _, _ in JOINT_POINTS].index("top_center")


def ranked_designs(report_dir: Path) -> list[tuple[float, Path, str]]:
    """(max error, episode path, actuator kind) of every design of a reference-evaluate directory, worst first."""
    out = []
    for part, data_dir in SOURCES.items():
        for d in json.loads((report_dir / part / "report.json").read_text())["designs"]:
            out.append((d["max_rel_error"], ROOT / data_dir / d["name"], d.get("actuators", "unknown")))
    return sorted(out, key=lambda x: -x[0])


def fixed_joint_points(f, points: np.ndarray) -> np.ndarray:
    """[F, P, 3] -> [F, n, 3] the points of the design's fixed joint (learn.diagnose.blocks: joints first)."""
    j = int(np.argmax(f.joint_bc[:, JOINT.bc.slice("fixed")][:, 0]))
    return blocks(points, f.incidence.n_joints)[0][:, j]


def anatomy(model, first, f, starts: list[int]) -> dict:
    """The final-frame measures of the module doc for one design (fractions of the design size)."""
    size = f.design_size
    P = rollout(model, f, steps=f.n_frames - 1, t=f.t).local_points.astype(np.float64)  # [F, N, 3]
    Q, x0 = f.fea_points.astype(np.float64), f.fea_points[0].astype(np.float64)
    err = lambda a, b: float(np.linalg.norm(a - b, axis=-1).max() / size)  # noqa: E731
    dp, dq = P[-1] - x0, Q[-1] - x0
    reach = np.linalg.norm(Q[-1, :, :2], axis=-1)
    joint_q, joint_p = fixed_joint_points(f, Q), fixed_joint_points(f, P)
    turn = best_rotation(joint_q[0], joint_q[-1]) @ best_rotation(joint_p[0], joint_p[-1]).T
    centre = joint_q[0, TOP_CENTER]
    static, t = static_from(f.joint_bc, f.beam_bc, f.incidence), torch.as_tensor(f.t, dtype=torch.float32)
    from_frame = []
    for s in starts:
        js, bs = unroll(first, torch.as_tensor(f.joint_state[s]), torch.as_tensor(f.beam_state[s]), static, t[s:])
        from_frame.append(err(rebuild_all_points(js, bs).numpy()[-1], Q[-1]))
    return {"error": err(P[-1], Q[-1]), "shape": float(shape_error(P[-1], Q[-1]) / size),
            "amplitude": float((dp * dq).sum() / (dp * dp).sum()),
            "hang": float(((P[-1, :, 2] - Q[-1, :, 2]) * reach).sum() / reach.sum() / size),
            "pinned_joint": err((P[-1] - centre) @ turn.T + centre, Q[-1]), "from_frame": from_frame}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True,
                    help="a checkpoint, several joined by ',' (an ensemble), or models/<name>")
    ap.add_argument("--report", required=True, help="a make reference-evaluate directory (52/ and fresh/ inside)")
    ap.add_argument("--worst", type=int, default=22,
                    help="designs set apart as the tail (22: those over 1.6 %% for the ft2 pair)")
    ap.add_argument("--starts", default="0,3,6,8,9", help="FEA frames the rollouts 'from frame s' start from")
    ap.add_argument("--out", default=None, help="markdown file (default: <report>/tail_anatomy.md)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    sources = ensemble.checkpoint_paths(a.checkpoint.split(","))
    model, _ = ensemble.load(sources)
    first = ensemble.members_of(model)[0]
    starts = [int(s) for s in a.starts.split(",")]
    designs = ranked_designs(Path(a.report))
    if not 1 <= a.worst < len(designs):
        raise SystemExit(f"--worst {a.worst}: must be in [1, {len(designs) - 1}] (the report's {len(designs)} designs)")
    features = load_features([p for _, p, _ in designs])
    frames = min(f.n_frames for f in features)
    if any(not 0 <= s < frames for s in starts):
        raise SystemExit(f"--starts {a.starts}: every frame must be in [0, {frames - 1}] (the episodes' frames)")
    with torch.inference_mode():
        rows = [{"name": p.name, "actuators": kind, **anatomy(model, first, f, starts)}
                for (_, p, kind), f in zip(designs, features)]
    pct = lambda x: f"{100 * x:.2f}"  # noqa: E731
    lines = [f"# The tail's anatomy: {a.checkpoint} on {a.report} ({len(rows)} designs, final frame)", "",
             f"Command: `{' '.join([Path(sys.executable).name, *sys.argv])}`; % of the design size; from frame s: "
             f"the first member alone.", "",
             "| design | actuators | error | shape | amplitude | hang | pinned joint turned | "
             + " | ".join(f"from frame {s}" for s in starts) + " |", "|---" * (7 + len(starts)) + "|"]
    for r in rows[:a.worst]:
        lines.append(f"| {r['name']} | {r['actuators']} | {pct(r['error'])} | {pct(r['shape'])} | {r['amplitude']:.3f} | "
                     f"{pct(r['hang'])} | {pct(r['pinned_joint'])} | " + " | ".join(pct(x) for x in r["from_frame"]) + " |")
    lines += ["", "| designs | error median / p95 | shape median / p95 | amplitude median | hang median | pinned joint "
              "turned: median / p95, better on | " + " | ".join(f"from frame {s}: median / p95 / > 1.6 %" for s in starts)
              + " |", "|---" * (6 + len(starts)) + "|"]
    for label, group in ((f"worst {a.worst}", rows[:a.worst]), ("the rest", rows[a.worst:]), ("all", rows)):
        col = lambda k: np.array([r[k] for r in group])  # noqa: E731
        e, pj, ff = col("error"), col("pinned_joint"), 100 * np.array([r["from_frame"] for r in group])
        lines.append(f"| {label} ({len(group)}) | {pct(np.median(e))} / {pct(np.percentile(e, 95))} | "
                     f"{pct(np.median(col('shape')))} / {pct(np.percentile(col('shape'), 95))} | "
                     f"{np.median(col('amplitude')):.3f} | {pct(np.median(col('hang')))} | "
                     f"{pct(np.median(pj))} / {pct(np.percentile(pj, 95))}, {int((pj < e).sum())} | "
                     + " | ".join(f"{np.median(ff[:, i]):.2f} / {np.percentile(ff[:, i], 95):.2f} / "
                                  f"{int((ff[:, i] > 1.6).sum())}" for i in range(len(starts))) + " |")
    out = Path(a.out) if a.out else Path(a.report) / "tail_anatomy.md"
    atomic.write_text(out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
