"""Fingerprints of episodes: is a regenerated data set the one a result was measured on?

    python -m data_schema.fingerprint DIR --write FILE.csv   # one row per episode: design digest + final shape
    python -m data_schema.fingerprint DIR --check FILE.csv   # exit 1 naming every episode that differs

Data sets are regenerated from seeds (a new machine, a lost disk), and a figure in the docs holds only for the
episodes it was measured on. A row holds the digest of the episode's design (the sampler's output with its
configuration, exact) and a few numbers of its final frame in mm (the FEA's answer): the largest and the
root-mean-square node displacement and the centroid, which a change of the solver, the material, the load or the
mesh moves (a single node moved alone may not show). `--check` compares the episodes present in both: the same
design, the same mesh sizes, every number within `--tol-mm` (0.01 mm by default: 1e-4 of a 100 mm design, a hundred
times below the learned simulator's 1 % target, and ~500x the float32 resolution of a position at 200 mm). Episodes
only on one side are counted, not failed: a data set being regenerated is checked as far as it has got.
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import os
import sys
from pathlib import Path

import h5py
import numpy as np

from data_schema.atomic import write_csv
from data_schema.validate import episode_files

__all__ = ["COLUMNS", "TOL_MM", "fingerprint", "read_fingerprints", "differences", "main"]

TOL_MM = 0.01
COUNTS = ("n_nodes", "n_cells", "n_frames")
NUMBERS = ("final_max_disp_mm", "final_rms_disp_mm", "final_centroid_x_mm", "final_centroid_y_mm",
           "final_centroid_z_mm")
COLUMNS = ("episode", "design_sha256", *COUNTS, *NUMBERS)


def design_digest(design_json: str) -> str:
    """sha256 of the design JSON with its keys sorted (independent of how the writer ordered them)."""
    canonical = json.dumps(json.loads(design_json), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


def fingerprint(path: str | os.PathLike) -> dict:
    """The fingerprint row of one episode file (reads the design, the reference nodes and the last frame only)."""
    with h5py.File(path, "r") as h5:
        design_json = h5["design"].attrs["design_json"]
        x0 = h5["mesh/node_xyz0"][()]
        frames = h5["frames/node_xyz"]
        x = frames[frames.shape[0] - 1].astype(np.float64)
        row = {"episode": Path(path).name,
               "design_sha256": design_digest(design_json.decode() if isinstance(design_json, bytes) else design_json),
               "n_nodes": x0.shape[0], "n_cells": h5["mesh/cell_key"].shape[0], "n_frames": frames.shape[0]}
    u = np.linalg.norm(x - x0, axis=1)
    centroid = x.mean(axis=0)
    row.update(final_max_disp_mm=float(u.max()), final_rms_disp_mm=float(np.sqrt((u ** 2).mean())),
               final_centroid_x_mm=float(centroid[0]), final_centroid_y_mm=float(centroid[1]),
               final_centroid_z_mm=float(centroid[2]))
    return row


def write_fingerprints(path: str | os.PathLike, rows: list[dict], source: str = "") -> Path:
    """Rows to a CSV, atomically (numbers in mm to 1e-4 mm, well inside the check's tolerance)."""
    out = [{**r, **{k: f"{r[k]:.4f}" for k in NUMBERS}} for r in rows]
    comments = ["data_schema.fingerprint: one row per episode; lengths in mm (final frame vs reference)"]
    if source:
        comments.append(f"source: {source}")
    return write_csv(path, out, list(COLUMNS), comments=comments)


def read_fingerprints(path: str | os.PathLike) -> dict[str, dict]:
    """{episode: row} from a fingerprint CSV; a missing column is an error naming it."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(line for line in f if not line.startswith("#")))
    missing = [c for c in COLUMNS if rows and c not in rows[0]]
    if missing:
        raise ValueError(f"{path}: fingerprint CSV lacks column(s) {missing}; expected {list(COLUMNS)}")
    return {r["episode"]: r for r in rows}


def differences(reference: dict[str, dict], rows: list[dict], tol_mm: float = TOL_MM,
                round_off: list[str] | None = None) -> list[str]:
    """Every way the rows differ from the reference, as 'episode: field: ours vs reference' (episodes in both).
    A design whose digest differs while its mesh sizes and final shape agree within tol_mm is the same design
    written with other last bits: the sampler's sin, cos and sqrt round differently on another CPU (numpy's SIMD
    paths: AVX512 vs AVX2; session 28: 72 of the first 100 episodes, final shapes equal to 1e-4 mm). Such episodes
    are listed in `round_off` (when given), not as differences; a design that is really another one moves the
    final shape far beyond the tolerance."""
    if not (tol_mm >= 0 and math.isfinite(tol_mm)):
        raise ValueError(f"tol_mm = {tol_mm}: must be a finite number >= 0 (mm)")
    out = []
    for row in rows:
        ref = reference.get(row["episode"])
        if ref is None:
            continue
        shape = [f"{row['episode']}: {k}: {row[k]} vs {ref[k]}" for k in COUNTS if int(row[k]) != int(ref[k])]
        shape += [f"{row['episode']}: {k}: {float(row[k]):.4f} vs {float(ref[k]):.4f} mm (tolerance {tol_mm} mm)"
                  for k in NUMBERS if not abs(float(row[k]) - float(ref[k])) <= tol_mm]
        if row["design_sha256"] != ref["design_sha256"]:
            digests = f"({row['design_sha256'][:12]} vs {ref['design_sha256'][:12]})"
            if shape:
                out.append(f"{row['episode']}: design_sha256: another design {digests}: the sampler or its seed "
                           "changed")
            elif round_off is not None:
                round_off.append(f"{row['episode']}: design_sha256 {digests} differs, the final shape agrees within "
                                 f"{tol_mm} mm: the design's last bits (CPU round-off)")
            continue
        out += shape
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m data_schema.fingerprint", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", help="episode files or directories holding them")
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--write", metavar="CSV", help="write the fingerprints of these episodes to CSV")
    action.add_argument("--check", metavar="CSV", help="compare these episodes with the fingerprints in CSV")
    parser.add_argument("--tol-mm", type=float, default=TOL_MM, help=f"tolerance of the numbers (mm; {TOL_MM})")
    args = parser.parse_args(argv)
    if not (args.tol_mm >= 0 and math.isfinite(args.tol_mm)):
        parser.error(f"--tol-mm {args.tol_mm}: must be a finite number >= 0 (mm)")
    missing = [p for p in args.paths if not Path(p).exists()]
    if missing:
        parser.error(f"paths {missing}: not found")
    files = episode_files(args.paths)
    if not files:
        parser.error(f"paths {args.paths}: no *.h5 episodes found")
    rows = [fingerprint(p) for p in files]
    if args.write:
        write_fingerprints(args.write, rows, source=" ".join(map(str, args.paths)))
        print(f"{len(rows)} fingerprints -> {args.write}")
        return 0
    reference = read_fingerprints(args.check)
    round_off: list[str] = []
    problems = differences(reference, rows, args.tol_mm, round_off)
    for p in round_off:
        print(f"ROUND-OFF {p}")
    for p in problems:
        print(f"DIFFERS {p}")
    both = sum(r["episode"] in reference for r in rows)
    print(f"{both} episodes in both: {len({p.split(':')[0] for p in problems})} differ ({len(round_off)} more equal "
          f"but for the design's last bits); {len(rows) - both} only here, {len(reference) - both} only in "
          f"{args.check}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
