"""How much does the FEA's final shape move when the design moves by far less than a printer's tolerance?

For each chosen episode of a data directory, every joint centre is jittered by a vector uniform over a disk of
radius --jitter-mm (seeded by the episode number), the design is solved again exactly as the factory solves it
(fea_factory.generate.run_episode, the default solve settings), and the final frame is compared node by node (the
same tuple keys) with the stored episode. The ratio of output change to input change says whether the design ->
shape map is smooth at the scale of the learned simulator's error targets (0.5-1 % of the design size) or whether
near-identical designs part ways (snap-through, a closed bowl folding either way): a floor no learned model on
these labels can beat. Writes sensitivity.csv and sensitivity.md (machine, command) under --out.

    .venv/bin/python scripts/fea_sensitivity.py --episodes 207,14,218,243,9,146,101,77 --jitter-mm 0.1
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from omegaconf import OmegaConf  # noqa: E402

from data_schema import atomic  # noqa: E402
from data_schema.episode import read_episode  # noqa: E402
from fea_factory.design import Design  # noqa: E402
from fea_factory.generate import episode_path, run_episode  # noqa: E402
from fea_factory.sample import disk_jitter  # noqa: E402
from tradeoff import machine  # noqa: E402  (scripts/tradeoff.py)


def jittered(design: Design, r_max: float, seed: int) -> Design:
    """A copy of `design` with every joint centre moved by a vector uniform over the disk of radius r_max (mm)."""
    out = Design.from_dict(design.to_dict())
    out.joint_xy = out.joint_xy + disk_jitter(np.random.default_rng(seed), r_max, (design.n_joints,))
    return out


def failed(row: dict) -> str:
    """A failed perturbed solve as a table cell: its status, and where it stopped when it diverged."""
    if "last_t" not in row:
        return row["status"]
    return (f"{row['status']} at t = {row['last_t']:.3f}, clearance {row.get('last_clearance_mm', float('nan')):.2f} mm"
            f" (blocks {row.get('last_clearance_blocks', '?')})")


def final_shape_change(a, b) -> dict:
    """Two episodes of one topology (equal node keys) -> the largest node distance at frame 0 (the input change)
    and at the last frame (the output change), in mm and as a fraction of a's design size; and a's own motion."""
    if a.node_key.shape != b.node_key.shape or not np.array_equal(a.node_key, b.node_key):
        raise ValueError("episodes differ in node keys: not the same design topology and mesh")
    dist = lambda x, y: float(np.linalg.norm(x - y, axis=-1).max())  # noqa: E731
    size = float(a.design_size)
    d_in, d_out = dist(a.node_xyz[0], b.node_xyz[0]), dist(a.node_xyz[-1], b.node_xyz[-1])
    return {"design_size_mm": size, "input_change_mm": d_in, "output_change_mm": d_out,
            "output_change_rel": d_out / size, "amplification": d_out / d_in if d_in > 0 else float("inf"),
            "fea_motion_rel": dist(a.node_xyz[-1], a.node_xyz[0]) / size}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data-dir", default="data/ds_default")
    p.add_argument("--episodes", required=True, help="comma-separated episode numbers, e.g. 207,14,101")
    p.add_argument("--jitter-mm", type=float, default=0.1)
    p.add_argument("--np", type=int, default=1, help="MPI ranks per solve")
    p.add_argument("--out", default="reports/fea_sensitivity")
    a = p.parse_args()
    if not a.jitter_mm > 0:
        raise SystemExit(f"--jitter-mm={a.jitter_mm}: must be > 0")
    items = [x.strip() for x in a.episodes.split(",")]
    if not all(x.isdigit() for x in items):
        raise SystemExit(f"--episodes={a.episodes!r}: must be comma-separated episode numbers >= 0, e.g. 207,14,101")
    data, out = Path(a.data_dir), Path(a.out)
    solved = out / "episodes"
    solved.mkdir(parents=True, exist_ok=True)
    rows = []
    for i in (int(x) for x in items):
        source = episode_path(data, i)
        design_file = data / "designs" / f"episode_{i:05d}.json"
        if not source.exists() or not design_file.exists():
            raise SystemExit(f"episode {i}: {source} or {design_file} is missing")
        if not episode_path(solved, i).exists():  # resumable: a solved perturbation is kept
            record = run_episode(i, jittered(Design.load(design_file), a.jitter_mm, i), solved,
                                 OmegaConf.create({"np": a.np, "seed": 0}), [])
            if record["status"] != "ok":  # where it stopped and how close the grid came to itself (fea_factory)
                where = {k: record[k] for k in ("last_t", "last_clearance_mm", "last_clearance_blocks") if k in record}
                print(f"episode {i}: perturbed solve {record['status']}: {record.get('reason', '')} {where}", flush=True)
                rows.append({"episode": i, "status": record["status"], **where})
                continue
        row = {"episode": i, "status": "ok",
               **final_shape_change(read_episode(source), read_episode(episode_path(solved, i)))}
        rows.append(row)
        print(f"episode {i}: input moved {row['input_change_mm']:.3f} mm, final shape {row['output_change_mm']:.3f} mm"
              f" = {100 * row['output_change_rel']:.3f} % of {row['design_size_mm']:.0f} mm "
              f"(x{row['amplification']:.1f}; FEA motion {100 * row['fea_motion_rel']:.0f} %)", flush=True)
    fields = ["episode", "status", "design_size_mm", "input_change_mm", "output_change_mm", "output_change_rel",
              "amplification", "fea_motion_rel", "last_t", "last_clearance_mm"]
    atomic.write_csv(out / "sensitivity.csv", [{k: r.get(k, "") for k in fields} for r in rows], fields)
    lines = [f"# FEA final-shape sensitivity to a {a.jitter_mm} mm joint jitter ({data})", "",
             f"Machine: {machine()}. Command: `{' '.join([Path(sys.executable).name, *sys.argv])}`", "",
             "| episode | input change (mm) | final-shape change (mm) | % of design size | amplification | FEA motion |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['episode']} | {r['input_change_mm']:.3f} | {r['output_change_mm']:.3f} | "
              f"{100 * r['output_change_rel']:.3f} % | x{r['amplification']:.1f} | {100 * r['fea_motion_rel']:.0f} % |"
              if r["status"] == "ok" else f"| {r['episode']} | {failed(r)} | | | | |" for r in rows]
    atomic.write_text(out / "sensitivity.md", "\n".join(lines) + "\n")
    print(f"-> {out / 'sensitivity.md'}")


if __name__ == "__main__":
    main()
