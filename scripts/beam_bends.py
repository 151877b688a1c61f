"""How much of each beam's bend in the FEA is its own, and how much the grid sets: bends of the sampled designs against
the free actuator's.

    .venv/bin/python scripts/beam_bends.py data/ds_default [--max 260] [--out reports/beam_bends]

A free actuator bends at a constant curvature: conf/calibrate.yaml's `target_deg` over its clear `length` (75 deg at
50 mm: sigma is calibrated to that). In a grid every beam's ends sit on joints that other beams turn too, so a beam
bends as far as the loops of the grid let it (gravity aside). Per beam, at the final frame: the bend, the signed angle
between its end and start cross-sections about the start section's width axis (the angle fea_factory.calibrate
measures on the free actuator), against the free bend (curvature x clear length, sign of its kind; 0 for a passive
beam). Writes beam_bends.md (per kind: median and 10-90 % range of bend / free bend, the correlation) and
beam_bends.png (bend vs free bend, one point per beam). When the bends scatter widely about the free ones, a beam's
shape is a property of the whole grid, not of the beam: what a learned step has to get from its neighbours.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib
import numpy as np
import yaml

from learn.dataset import load_features
from learn.graph import BEAM, BEAM_KINDS

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def signed_bends_deg(beam_state: np.ndarray) -> np.ndarray:
    """[..., B, S] beam states -> [..., B] the signed angle (deg) from the start cross-section's height vector to the
    end one's, about the start section's width axis."""
    g = BEAM.geometry
    w0 = unit(beam_state[..., g.slice("start_width")])
    h0 = unit(beam_state[..., g.slice("start_height")])
    h1 = unit(beam_state[..., g.slice("end_height")])
    return np.degrees(np.arctan2((np.cross(h0, h1) * w0).sum(-1), (h0 * h1).sum(-1)))


def clear_lengths(beam_state: np.ndarray) -> np.ndarray:
    """[B, S] the flat design's beam states -> [B] start-to-end section distance (mm): the clear length."""
    g = BEAM.geometry
    return np.linalg.norm(beam_state[:, g.slice("end_center")] - beam_state[:, g.slice("start_center")], axis=-1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("--max", type=int, default=0, help="the first N episodes only (0: all)")
    ap.add_argument("--out", type=Path, default=Path("reports/beam_bends"))
    args = ap.parse_args()
    calib = yaml.safe_load((ROOT / "conf" / "calibrate.yaml").read_text())
    curvature = float(calib["target_deg"]) / float(calib["length"])  # deg / mm of a free actuator
    paths = sorted(args.data_dir.glob("*.h5"))[: args.max or None]
    rows = {k: [] for k in BEAM_KINDS}  # (free, actual)
    for f in load_features(paths):
        kinds = np.argmax(f.beam_bc[:, [BEAM.bc.names().index(f"kind_{k}") for k in BEAM_KINDS]], axis=1)
        actual = signed_bends_deg(f.beam_state[-1])
        length = clear_lengths(f.beam_state[0])
        for b, k in enumerate(kinds):
            sign = {"up": 1.0, "down": -1.0, "passive": 0.0}[BEAM_KINDS[k]]
            rows[BEAM_KINDS[k]].append((sign * curvature * length[b], actual[b]))
    up = np.array(rows["up"])
    # the free actuator's sign convention: whichever sign the "up" beams bend with on the whole
    flip = -1.0 if len(up) and np.median(up[:, 1]) < 0 else 1.0
    args.out.mkdir(parents=True, exist_ok=True)
    lines = [f"# Beam bends at the final frame, {len(paths)} episodes of {args.data_dir}", "",
             f"Free actuator: {calib['target_deg']} deg over {calib['length']} mm (conf/calibrate.yaml), "
             f"{curvature:.2f} deg/mm. Command: `.venv/bin/python scripts/beam_bends.py {args.data_dir}"
             f"{f' --max {args.max}' if args.max else ''} --out {args.out}`.", "",
             "| kind | beams | free bend, median (deg) | FEA bend, median (deg) | bend / free: median | 10-90 % | "
             "correlation with the free bend |", "|---|---|---|---|---|---|---|"]
    fig, ax = plt.subplots(figsize=(5.5, 5))
    for kind, pts in rows.items():
        if not pts:
            continue
        p = np.array(pts)
        free, actual = p[:, 0], flip * p[:, 1]
        ax.scatter(free, actual, s=6, alpha=0.5, label=f"{kind} ({len(p)})")
        if kind == "passive":
            lines.append(f"| passive | {len(p)} | 0 | {np.median(actual):.1f} (|bend| median "
                         f"{np.median(np.abs(actual)):.1f}) | - | - | - |")
            continue
        ratio = actual / free
        lines.append(f"| {kind} | {len(p)} | {np.median(free):.1f} | {np.median(actual):.1f} | "
                     f"{np.median(ratio):.2f} | {np.percentile(ratio, 10):.2f} to {np.percentile(ratio, 90):.2f} | "
                     f"{np.corrcoef(free, actual)[0, 1]:.2f} |")
    lim = np.abs(ax.get_xlim() + ax.get_ylim()).max()
    ax.plot([-lim, lim], [-lim, lim], "k:", lw=1, label="free actuator")
    ax.set_xlabel("free bend, curvature x clear length (deg)")
    ax.set_ylabel("FEA bend at the final frame (deg)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "beam_bends.png", dpi=110)
    (args.out / "beam_bends.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
