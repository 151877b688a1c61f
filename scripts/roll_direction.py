"""Which way the FEA rolls a grid whose actuators all bend alike, against the grid's spans.

    .venv/bin/python scripts/roll_direction.py data/ds_default [--out reports/roll_direction]

A flat grid whose actuators all bend one way asks for the same curvature along its rows and its columns: a bowl,
which a sheet cannot take without stretching. So it rolls one way (a near-cylinder) or snaps into a bowl, a
bifurcation; the worst answers of every learned model so far are such designs answered unrolled (session 29). Per
all-up or all-down design (learn.roll): the grid's span along i over its span along j (the flat joint centres' extents
along the mean direction of its beams along i and along j; learn.model.beam_spans gives each beam its own), and the
final frame's extents along those directions over the flat ones, s_i and s_j. Rolled: |s_i - s_j| > ROLLED. Writes
roll_direction.md (the count that rolled, and how many along the longer span), roll_direction.csv (per design) and
roll_direction.png (s_i - s_j against log(span_i / span_j)).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib
import numpy as np

from data_schema import atomic
from learn.dataset import episode_paths, load_features
from learn.roll import ONE_KIND, ROLLED, shrinks, span_ratio

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def roll_of(f) -> dict:
    ratio = span_ratio(f)
    s_i, s_j = shrinks(f, f.fea_points)
    rolled = abs(s_i - s_j) > ROLLED
    return {"episode": f.name, "actuators": f.actuators, "family": f.family, "span_ratio": ratio,
            "s_i": s_i, "s_j": s_j, "rolled": rolled, "along_longer": rolled and (s_i < s_j) == (ratio > 1)}


def summary(rows: list[dict]) -> str:
    rolled = [r for r in rows if r["rolled"]]
    longer = sum(r["along_longer"] for r in rolled)
    near_square = [r for r in rows if abs(np.log(r["span_ratio"])) < np.log(1.1)]
    lines = [f"# Which way all-up / all-down grids roll in the FEA ({len(rows)} designs)", "",
             f"- rolled (|s_i - s_j| > {ROLLED}): {len(rolled)} of {len(rows)}; along the longer span: {longer} of "
             f"{len(rolled)}",
             f"- near-square (spans within 10 %): {len(near_square)}, of them rolled: "
             f"{sum(r['rolled'] for r in near_square)}",
             "", "| episode | actuators | span_i / span_j | s_i | s_j | rolled | along the longer span |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['episode']} | {r['actuators']} | {r['span_ratio']:.2f} | {r['s_i']:.2f} | {r['s_j']:.2f} | "
              f"{'yes' if r['rolled'] else 'no'} | {'yes' if r['along_longer'] else '-'} |" for r in rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("--out", type=Path, default=Path("reports/roll_direction"))
    args = ap.parse_args()
    paths = episode_paths(args.data_dir)
    if not paths:
        raise SystemExit(f"no episodes in {args.data_dir}")
    rows = [roll_of(f) for f in load_features(paths) if f.actuators in ONE_KIND]
    if not rows:
        raise SystemExit(f"no all-up or all-down designs among the {len(paths)} episodes of {args.data_dir}")
    text = summary(rows)
    atomic.write_text(args.out / "roll_direction.md", text)
    atomic.write_csv(args.out / "roll_direction.csv", rows, list(rows[0]))
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for kind, marker in (("all up", "^"), ("all down", "v")):
        mine = [r for r in rows if r["actuators"] == kind]
        ax.scatter([np.log(r["span_ratio"]) for r in mine], [r["s_i"] - r["s_j"] for r in mine], marker=marker,
                   label=kind)
    for y in (-ROLLED, ROLLED):
        ax.axhline(y, color="grey", lw=0.5, ls="--")
    ax.axvline(0.0, color="grey", lw=0.5)
    ax.set_xlabel("log(span along i / span along j) of the flat grid")
    ax.set_ylabel("s_i - s_j (final / flat extents)")
    ax.set_title("< 0: curled along i; > 0: along j (FEA, final frame)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "roll_direction.png", dpi=120)
    print("\n".join(text.split("\n")[:4]) + f"\nwritten to {args.out}")


if __name__ == "__main__":
    main()
