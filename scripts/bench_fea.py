"""FEA benchmark: one fixed 3x3 design through every mesh preset, serial vs mpirun -n 2, direct vs iterative.

    .venv/bin/python scripts/bench_fea.py --out reports/bench_fea [--presets coarse,default,fine] [--quick]

Writes bench.csv, bench.md (table with machine and command) and bench.png (wall time vs tip error).
The tip error of each run is the max node distance to the finest preset's run, on the nodes all presets
share (the joints' corner nodes, keyed (block, 0|nw-1, 0|nw-1, 0|nh-1)), as a fraction of the design size.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from data_schema import atomic  # noqa: E402

from fea_factory.compare import bench_design, corner_positions, run_solve  # noqa: E402


def run(design_file: Path, out: Path, preset: str, np_: int, linear: str) -> dict:
    return run_solve(design_file, out, [f"mesh={preset}", f"solver.linear_solver={linear}"], ranks=np_)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="reports/bench_fea")
    ap.add_argument("--presets", default="coarse,default,fine")
    ap.add_argument("--quick", action="store_true", help="serial direct only (minutes less)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    presets = args.presets.split(",")
    design = bench_design()
    size = design.size
    tmp = Path(tempfile.mkdtemp(prefix="bench_fea_"))
    design.save(tmp / "design.json")
    cases = [(p, 1, "direct") for p in presets]
    if not args.quick:
        cases += [(p, 2, "direct") for p in presets] + [(presets[0], 1, "iterative")]
    rows, episodes = [], {}
    for preset, np_, linear in cases:
        res = run(tmp / "design.json", tmp / f"{preset}_{np_}_{linear}.h5", preset, np_, linear)
        ep = res.pop("episode", None)
        if ep is not None:
            episodes[(preset, np_, linear)] = ep
        rows.append({"preset": preset, "ranks": np_, "linear_solver": linear, **res})
        print(json.dumps(rows[-1]), flush=True)
    ref_key = (presets[-1], 1, "direct")
    ref = corner_positions(episodes[ref_key]) if ref_key in episodes else None
    for row in rows:
        ep = episodes.get((row["preset"], row["ranks"], row["linear_solver"]))
        if ep is not None and ref is not None:
            row["max_corner_diff_mm"] = float(np.linalg.norm(corner_positions(ep) - ref, axis=1).max())
            row["rel_error_vs_finest"] = row["max_corner_diff_mm"] / size
    keys = ["preset", "ranks", "linear_solver", "status", "cells", "nodes", "increments", "newton", "cutbacks",
            "wall_jit_s", "wall_solve_s", "wall_total_s", "max_corner_diff_mm", "rel_error_vs_finest"]
    atomic.write_csv(out / "bench.csv", rows, keys)
    machine = f"{platform.node()} {platform.processor() or platform.machine()}, {os.cpu_count()} cores"
    lines = [f"# FEA benchmark ({design.n_joints} joints, {design.n_beams} beams, size {size:.0f} mm)", "",
             f"Machine: {machine}. Command: `{' '.join([Path(sys.executable).name, *sys.argv])}`", "",
             "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        lines.append("| " + " | ".join(f"{r.get(k):.4g}" if isinstance(r.get(k), float) else str(r.get(k, ""))
                                       for k in keys) + " |")
    atomic.write_text(out / "bench.md", "\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for r in rows:
        if "rel_error_vs_finest" in r:
            ax.scatter(r["wall_total_s"], max(r["rel_error_vs_finest"], 1e-6))
            ax.annotate(f"{r['preset']} n{r['ranks']} {r['linear_solver'][:3]}",
                        (r["wall_total_s"], max(r["rel_error_vs_finest"], 1e-6)), fontsize=7)
    ax.set_xscale("log"), ax.set_yscale("log")
    ax.set_xlabel("episode wall time (s)"), ax.set_ylabel("max corner error / design size")
    ax.axhline(0.01, ls="--", c="gray")
    fig.tight_layout()
    fig.savefig(out / "bench.png", dpi=120)
    print((out / "bench.md").read_text())


if __name__ == "__main__":
    main()
