"""Run the stability matrix of fea_factory.extremes and write a table.

    .venv/bin/python scripts/stability_matrix.py [--out reports/stability] [--cases sigma_3x,gravity_10x]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from data_schema import atomic  # noqa: E402

KEYS = ["case", "quantity", "value", "must_converge", "status", "increments", "newton", "cutbacks", "finite",
        "max_disp_mm", "max_disp_rel", "wall_s", "reason"]


def main() -> None:
    from tqdm import tqdm

    from fea_factory.extremes import CASES, run_case

    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="reports/stability")
    ap.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    args = ap.parse_args()
    chosen = [c for c in CASES if not args.cases or c.name in args.cases.split(",")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in tqdm(chosen, desc="stability cases"):
        rows.append(run_case(case))
        tqdm.write(json.dumps(rows[-1]))
    atomic.write_csv(out / "stability.csv", rows, KEYS)
    fmt = lambda v: f"{v:.3g}" if isinstance(v, float) else ("" if v is None else str(v))  # noqa: E731
    lines = ["# Stability at the extremes", "",
             f"Machine: {platform.node()}, {os.cpu_count()} cores. Command: `{' '.join(sys.argv)}`", "",
             "| " + " | ".join(KEYS) + " |", "|" + "---|" * len(KEYS)]
    lines += ["| " + " | ".join(fmt(r.get(k)) for k in KEYS) + " |" for r in rows]
    atomic.write_text(out / "stability.md", "\n".join(lines) + "\n")
    print((out / "stability.md").read_text())


if __name__ == "__main__":
    main()
