"""The learned simulator outside its training ranges: FEA episodes of designs the training set never held, rolled
out with a checkpoint, each marked valid or flagged by the validity check (learn.validity).

    .venv/bin/python scripts/learned_extremes.py --checkpoint runs/train/best.pt --out reports/learned_extremes

Every case generates `--n` episodes with the factory (fea_factory.generate, resumable: a re-run reuses them) into
<data>/<case>/, then runs learn.evaluate with split=all on them; <out>/summary.md and summary.json collect the
error and the verdict of every design. Episode indices start at 1000, beyond the training set's (0 .. N-1 of
`make dataset`), so the in-range control designs are new draws from the training distribution.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from data_schema import atomic  # noqa: E402

from fea_factory.extremes import NOMINAL_SIGMA  # noqa: E402
from learn.evaluate import evaluate  # noqa: E402

# name, what is outside the training range, generator overrides
CASES = [
    ("in_range", "nothing (control: new draws of the training distribution)", []),
    ("long_beams", "lattice step 130-150 mm (training: 50-100 mm)",
     ["grid.spacing_x=[130.0,150.0]", "grid.spacing_y=[130.0,150.0]"]),
    ("sigma_2x", f"residual stress {2 * NOMINAL_SIGMA:.4f} MPa (training: {NOMINAL_SIGMA} MPa)",
     [f"material.residual_stress.sigma={2 * NOMINAL_SIGMA}"]),
    ("gravity_5x", "body force 5 g (training: 1 g)", ["scene.g=49050.0"]),
    ("grid_7x3", "7 x 3 joints, 35-41 mm steps (training: 3 x 3, 50-100 mm)", ["grid=g7x3"]),
]


def generate(case: str, overrides: list[str], data: Path, n: int, jobs: int) -> Path:
    out = data / case
    cmd = [sys.executable, "-m", "fea_factory.generate", f"n={n}", "start=1000", f"out={out}", f"jobs={jobs}",
           "np=1", "progress=false", *overrides]
    subprocess.run(cmd, cwd=REPO, check=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="runs/train/best.pt")
    ap.add_argument("--out", default="reports/learned_extremes")
    ap.add_argument("--data", default="data/extremes", help="where the FEA episodes of the cases go")
    ap.add_argument("--n", type=int, default=2, help="episodes per case")
    ap.add_argument("--jobs", type=int, default=1, help="episodes solved at the same time")
    ap.add_argument("--cases", default=",".join(c[0] for c in CASES))
    args = ap.parse_args()
    wanted = args.cases.split(",")
    unknown = sorted(set(wanted) - {c[0] for c in CASES})
    if unknown:
        ap.error(f"--cases: unknown {unknown}; allowed {[c[0] for c in CASES]}")
    out = Path(args.out)
    rows = []
    for name, what, overrides in (c for c in CASES if c[0] in wanted):
        episodes = generate(name, overrides, Path(args.data), args.n, args.jobs)
        with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
            cfg = compose(config_name="evaluate", overrides=[
                f"checkpoint={args.checkpoint}", f"data_dir={episodes}", "split=all", f"out_dir={out / name}",
                "timing_repeats=1"])
        report = evaluate(cfg)
        for d in report["designs"]:
            rows.append({"case": name, "outside": what, "design": d["name"], "family": d["family"],
                         "max_rel_error": d["max_rel_error"], "valid": d["valid"],
                         "reasons": d["validity"]["reasons"],
                         "out_of_range_fraction": d["validity"]["out_of_range_fraction"],
                         "max_dislocation_mm": d["validity"]["max_dislocation_mm"]})
    atomic.write_text(out / "summary.json", json.dumps({"checkpoint": args.checkpoint, "designs": rows}, indent=1))
    lines = [f"# Learned simulator outside its training ranges ({args.checkpoint})", "",
             "| case | outside the training range | design | max err / size | verdict |", "|---|---|---|---|---|"]
    for r in rows:
        verdict = "valid" if r["valid"] else "FLAGGED: " + "; ".join(r["reasons"])
        lines.append(f"| {r['case']} | {r['outside']} | {r['design']} | {100 * r['max_rel_error']:.2f}% | {verdict} |")
    atomic.write_text(out / "summary.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
