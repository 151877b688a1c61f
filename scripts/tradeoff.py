"""The speed/accuracy trade, measured: a fixed panel of designs through every FEA setting that buys speed with
accuracy (mesh preset, load increments, linear solver, MPI ranks) and optionally learned simulators, each measured
against the finest FEA reference of the same run.

    .venv/bin/python scripts/tradeoff.py [--panel reduced|full] [--out reports/tradeoff]
                                         [--checkpoints runs/train/best.pt,...] [--install] [--list] [--resume]
    make tradeoff [PANEL=full] [OUT=...] [CHECKPOINTS=a.pt,b.pt] [INSTALL=1] [RESUME=1]

Writes OUT/tradeoff.csv (one row per design and setting), OUT/pareto.png (mean wall time vs worst max error per
setting, log axes, Pareto front marked and labelled) and OUT/summary.md (machine, command, tables, the cheapest
setting meeting 5 %, 2 %, 1 % and 0.5 %). --install also writes the per-setting FEA table to
conf/solver/tradeoff_table.csv, which `solver.tolerance=...` picks from (fea_factory.tradeoff).

Definitions
- error: distance of the joints' corner nodes (present at every mesh preset) to the reference run's, over every
  saved frame after t = 0 (t = 0.1 ... 1), divided by the design size; max and mean over nodes and frames.
  A learned simulator's joint corner points (rebuilt from its joint features) are compared the same way.
- reference: the `--reference` mesh preset (default fine), adaptive increments, direct solver, 1 rank. Rows on the
  reference mesh only measure solver/rank/increment differences (their error is a lower bound) and are never picked.
- wall_s: the solve's own wall time (episode provenance wall_total_s: mesh, JIT/kernel load, assembly, Newton,
  output; rank 0); process_s adds interpreter start-up, imports and mpirun. Learned: median rollout time of one
  design (TorchScript-compiled, 1 thread), all frames.
- peak_mb: peak resident memory of mpirun plus all its ranks, summed, polled every 0.1 s from /proc.
- dominated: a run still going after --dominated (default 1.5) x the time of the fastest finished run of the same
  design on a mesh at least as fine is stopped: that run is at least as accurate (same mesh: same converged
  answer, measured to 3 digits; finer mesh: more accurate) and faster, so the exact time changes no pick.
Runs are sequential, the reference first; every child inherits this process's niceness.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import platform
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from data_schema import atomic  # noqa: E402

from fea_factory.compare import corner_nodes, corner_positions, episode_error, run_solve  # noqa: E402
from fea_factory.tradeoff import (INCREMENT_MODES, LINEAR_SOLVERS, TABLE, Setting, TradeoffError,  # noqa: E402
                                  aggregate, pareto_front, pick, write_table)

TOLERANCES = (0.05, 0.02, 0.01, 0.005)
PANEL_SEED = 2024


@dataclass(frozen=True)
class PanelDesign:
    """A design of the panel: drawn by the sampler (conf/grid/<grid>.yaml with one family), fixed seed and index."""

    name: str
    grid: str
    family: str
    index: int

    def draw(self):
        from hydra import compose, initialize_config_dir

        from fea_factory.sample import sample_designs

        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            cfg = compose(config_name="sample", overrides=[
                "out=unused", f"grid={self.grid}", f"grid.family.random={int(self.family == 'random')}",
                f"grid.family.regular={int(self.family == 'regular')}"])
        return sample_designs(cfg.grid, cfg.blocks, n=1, seed=PANEL_SEED, start=self.index)[0]


DESIGNS = {
    "regular3x3": PanelDesign("regular3x3", "default", "regular", 0),  # rectangle, random actuators, 181 mm
    "random3x3": PanelDesign("random3x3", "default", "random", 2),  # jittered, random actuators, 138 mm
    "random7x3": PanelDesign("random7x3", "g7x3", "random", 2),  # jittered, random actuators, 228 mm
}


def panel(name: str, reference: str) -> tuple[list[PanelDesign], list[Setting]]:
    """(designs, settings) of a panel; settings[0] is the reference."""
    ref = Setting(reference)
    if name == "reduced":
        designs = [DESIGNS["regular3x3"], DESIGNS["random3x3"]]
        settings = [ref, Setting("coarse"), Setting("default"), Setting("medium"), Setting("default", "fixed10"),
                    Setting("default", "fixed20"), Setting("default", linear_solver="iterative"),
                    Setting("default", ranks=2)]
    elif name == "full":
        designs = list(DESIGNS.values())
        meshes = sorted({p.stem for p in (ROOT / "conf" / "mesh").glob("*.yaml")} - {reference},
                        key=_preset_size) + [reference]
        # every increment mode x linear solver on the cheaper meshes; on the reference mesh (errors only a lower
        # bound, never picked) just the speed knobs: iterative solver and 2 ranks
        # (base runs of every mesh first: they set the time caps of the variants, see time_cap)
        settings = [ref] + [Setting(m) for m in meshes[:-1]] + \
            [Setting(m, inc, lin) for m in meshes[:-1] for inc in INCREMENT_MODES for lin in LINEAR_SOLVERS
             if Setting(m, inc, lin) != Setting(m)] + [Setting(reference, linear_solver="iterative")] + \
            [Setting(m, ranks=2) for m in meshes]
    else:
        raise SystemExit(f"--panel {name!r}: must be reduced | full")
    return designs, settings


def _preset_size(name: str) -> int:
    from omegaconf import OmegaConf

    m = OmegaConf.load(ROOT / "conf" / "mesh" / f"{name}.yaml")
    return int(m.nodes_length) * int(m.nodes_width) ** 2 * int(m.nodes_height)


# ------------------------------------------------------------------------------------------------ FEA
def time_cap(s: Setting, done: list[tuple[Setting, float]], factor: float) -> tuple[float, Setting] | None:
    """(factor x seconds, that run) of the fastest finished run on a mesh at least as fine as s's, or None."""
    size = _preset_size(s.mesh)
    runs = [(t, d) for d, t in done if _preset_size(d.mesh) >= size]
    if not runs:
        return None
    t, d = min(runs, key=lambda x: x[0])
    return factor * t, d


def fea_row(pd: PanelDesign, design, s: Setting, res: dict) -> dict:
    return {"design": pd.name, "design_size_mm": round(design.size, 2), "setting": s.name, "kind": "fea",
            "mesh": s.mesh, "increments": s.increments, "linear_solver": s.linear_solver, "ranks": s.ranks,
            "status": res["status"], "wall_s": res.get("wall_total_s", math.nan), "process_s": res.get("process_s"),
            "newton": res.get("newton", math.nan), "increments_taken": res.get("increments"),
            "cutbacks": res.get("cutbacks"), "peak_mb": res.get("peak_mb"), "nodes": res.get("nodes"),
            "cells": res.get("cells"), "max_rel_error": math.nan, "mean_rel_error": math.nan,
            "max_error_mm": math.nan, "reason": str(res.get("reason") or "")[:300]}


# ------------------------------------------------------------------------------------------------ learned
def learned_name(path: Path) -> str:
    return f"learned:{path.parent.name}/{path.stem}" if path.parent.name else f"learned:{path.stem}"


def corner_point_index(point_nodes: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Index of the first rebuilt point standing for each node (-1: none). The joints' points come first, so a
    corner node shared with a beam end face maps to the joint's own prediction."""
    first: dict[int, int] = {}
    for p, node in enumerate(np.asarray(point_nodes)):
        first.setdefault(int(node), p)
    return np.array([first.get(int(n), -1) for n in nodes], dtype=np.int64)


def learned_row(model, ref_ep, name: str, pd_name: str, size: float, repeats: int = 5) -> dict:
    """Roll a learned simulator out on the reference episode's design (frame 0 and frame times only), time it and
    compare its rebuilt joint corner points with the reference's corner nodes."""
    import torch
    from omegaconf import OmegaConf

    from learn.evaluate import median_seconds
    from learn.features import extract
    from learn.rollout import compile_rollout, graph_inputs, rollout
    from learn.validity import check, thresholds

    torch.set_num_threads(1)
    f = extract(ref_ep, name=pd_name)
    compiled = compile_rollout(model, f)
    wall = median_seconds(lambda: compiled(*graph_inputs(f)), repeats)
    r = rollout(model, f, steps=f.n_frames - 1, t=f.t)
    idx = corner_point_index(r.point_nodes, corner_nodes(ref_ep))
    row = {"design": pd_name, "design_size_mm": round(size, 2), "setting": name, "kind": "learned", "mesh": "",
           "increments": "", "linear_solver": "", "ranks": 1, "status": "ok", "wall_s": wall, "process_s": None,
           "newton": math.nan, "peak_mb": None, "max_rel_error": math.nan, "mean_rel_error": math.nan,
           "max_error_mm": math.nan, "reason": ""}
    if (idx < 0).any():
        row.update(status="error", reason="the rollout's points do not include every joint corner node")
        return row
    ref = corner_positions(ref_ep, slice(1, None))
    d = np.linalg.norm(r.points[1:, idx] - ref, axis=-1)
    mx, mean = float(d.max() / size), float(d.mean() / size)
    limits = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "validity" / "default.yaml"))
    verdict = check(model, r, **thresholds(limits, model))
    row.update(max_rel_error=mx, mean_rel_error=mean, max_error_mm=float(d.max()))
    row["valid"] = bool(verdict.valid)
    if not verdict.valid:
        row["reason"] = "validity check: " + "; ".join(verdict.reasons)[:300]
    return row


# ------------------------------------------------------------------------------------------------ report
COLUMNS = ["design", "design_size_mm", "setting", "kind", "mesh", "increments", "linear_solver", "ranks", "status",
           "wall_s", "process_s", "newton", "increments_taken", "cutbacks", "peak_mb", "nodes", "cells",
           "max_rel_error", "mean_rel_error", "max_error_mm", "valid", "reason"]


def write_csv(path: Path, rows: list[dict]) -> None:
    atomic.write_csv(path, ({k: _fmt(r.get(k)) for k in COLUMNS} for r in rows), COLUMNS)


NUMERIC = ("design_size_mm", "ranks", "wall_s", "process_s", "newton", "increments_taken", "cutbacks", "peak_mb",
           "nodes", "cells", "max_rel_error", "mean_rel_error", "max_error_mm")


def read_csv(path: Path) -> list[dict]:
    """Rows as write_csv wrote them, numbers back as floats (empty: NaN; ranks: int), for --resume."""
    rows = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            for k in NUMERIC:
                r[k] = math.nan if r.get(k) in ("", None) else float(r[k])
            r["ranks"] = int(r["ranks"]) if math.isfinite(r["ranks"]) else r["ranks"]
            rows.append(r)
    return rows


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _pct(x) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{100 * x:.3g} %"


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{platform.node()}, {cpu}, {os.cpu_count()} cores, {platform.system()} {platform.release()}"


def cheapest(table: list[dict], tol: float, fea_only: bool) -> dict | None:
    """fea_factory.tradeoff.pick over the FEA rows (or every row), None when no setting meets tol."""
    try:
        return pick([t for t in table if t["kind"] == "fea" or not fea_only], tol)
    except TradeoffError:
        return None


def summarize(rows: list[dict], reference: Setting, reference_mesh: str) -> list[dict]:
    table = aggregate(rows, reference_mesh)
    kinds = {r["setting"]: r["kind"] for r in rows}
    for t in table:
        t["kind"] = kinds[t["setting"]]
        if t["kind"] == "learned":
            t["reference"] = 0
    front = pareto_front([t["wall_s"] if not t["reference"] else math.nan for t in table],
                         [t["max_rel_error"] for t in table])
    for t, on in zip(table, front):
        t["pareto"] = bool(on)
    return table


def plot(table: list[dict], out: Path, reference: Setting) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [t for t in table if math.isfinite(t["wall_s"]) and math.isfinite(t["max_rel_error"])]
    measured = [t["max_rel_error"] for t in ok if not t["reference"] and t["max_rel_error"] > 0]
    # reference-mesh rows: their discretisation error is not measured; drawn in a band below every measured error
    floor = min(measured + [min(TOLERANCES)]) / 4
    fig, ax = plt.subplots(figsize=(9, 6))
    colors = {"fea": "tab:blue", "learned": "tab:red"}
    n_ref = 0
    for t in ok:
        ref = bool(t["reference"])
        y = floor if ref else t["max_rel_error"]
        n_ref += ref
        ax.scatter(t["wall_s"], y, s=50 if t["pareto"] else 22, marker="v" if ref else "o",
                   facecolors="none" if ref else colors[t["kind"]], edgecolors=colors[t["kind"]], zorder=3)
        label = t["setting"] + (f" (vs reference {t['max_rel_error']:.1g})" if ref else "")
        dy = 9 * (n_ref % 4) - 11 if ref else 3  # stagger the reference rows' labels
        ax.annotate(label, (t["wall_s"], y), fontsize=7 if t["pareto"] else 6, xytext=(4, dy),
                    textcoords="offset points",
                    fontweight="bold" if t["pareto"] else "normal", color="black" if t["pareto"] else "dimgray",
                    rotation=0 if t["pareto"] or ref else 12)
    ax.axhspan(floor / 2, floor * 2, color="0.93", zorder=0)
    ax.text(0.99, floor / 1.9, "reference mesh: own discretisation error not measured", fontsize=7, color="gray",
            ha="right", va="bottom", transform=ax.get_yaxis_transform())
    front = sorted([t for t in ok if t["pareto"]], key=lambda t: t["wall_s"])
    if front:
        ax.step([t["wall_s"] for t in front], [t["max_rel_error"] for t in front], where="post",
                c="tab:green", lw=1.2, label="Pareto front", zorder=2)
    for tol in TOLERANCES:
        ax.axhline(tol, ls=":", c="gray", lw=0.8)
        ax.text(0.0, tol, f" {100 * tol:g} %", fontsize=7, color="gray",
                transform=ax.get_yaxis_transform(), va="bottom")
    if ok:  # room on the right for the labels
        walls = [t["wall_s"] for t in ok]
        ax.set_xlim(min(walls) / 2, max(walls) * 8)
        ax.set_ylim(floor / 2, max(max(t["max_rel_error"] for t in ok), max(TOLERANCES)) * 2)
    ax.set_xscale("log"), ax.set_yscale("log")
    ax.set_xlabel("wall time per design (s): FEA solve, or learned rollout")
    ax.set_ylabel("max joint-corner error / design size (worst design)")
    ax.set_title(f"speed vs accuracy against the FEA reference {reference.name}", fontsize=9)
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "pareto.png", dpi=130)
    plt.close(fig)


def markdown(rows, table, designs_info, reference, args, wall_total, load_before, load_after, learned_note) -> str:
    cmd = " ".join([Path(sys.executable).name, *sys.argv])
    lines = [f"# Speed/accuracy trade-off ({args.panel} panel)", "",
             f"- Machine: {machine()}; load average (1/5/15 min) {load_before} before, {load_after} after the run",
             f"- Command: `{cmd}` (panel wall time {wall_total:.0f} s)",
             *([f"- Note: {args.note}"] if args.note else []),
             f"- Reference: `{reference.name}` (per design, same run). Error = distance of the joints' corner nodes "
             "to the reference's over every saved frame after t = 0, / design size; rows on the reference mesh "
             "only measure solver/rank/increment differences (lower bound, never picked).",
             "- wall_s: solver wall time (provenance wall_total_s, rank 0); peak_mb: mpirun + all ranks, summed, "
             "polled every 0.1 s. Per setting: mean wall time and worst max error over the designs whose reference "
             "run succeeded; a setting that failed on any of them is never picked.",
             f"- Learned simulators: {learned_note}", "", "## Designs", "",
             "| design | sampler | family/shape | actuators | joints | size mm |", "|---|---|---|---|---|---|"]
    for d in designs_info:
        lines.append(f"| {d['name']} | grid={d['grid']} seed={PANEL_SEED} index={d['index']} | {d['family']} | "
                     f"{d['actuators']} | {d['joints']} | {d['size']:.1f} |")
    lines += ["", "## Cheapest setting meeting a tolerance (worst max error over the panel)", "",
              "| tolerance | cheapest FEA setting | wall s | max error | cheapest overall | wall s | max error |",
              "|---|---|---|---|---|---|---|"]
    for tol in TOLERANCES:
        cells = [f"{100 * tol:g} %"]
        for fea_only in (True, False):
            c = cheapest(table, tol, fea_only)
            cells += [f"`{c['setting']}`", f"{c['wall_s']:.3g}", _pct(c["max_rel_error"])] if c else \
                ["none measured", "", ""]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "## Per setting", "",
              "| setting | kind | designs ok | wall s (mean) | Newton its (mean) | peak MB | max error | mean error | "
              "Pareto |", "|---|---|---|---|---|---|---|---|---|"]
    for t in sorted(table, key=lambda t: (t["wall_s"], t["setting"])):
        ref = " (reference mesh)" if t["reference"] else ""
        lines.append(f"| `{t['setting']}`{ref} | {t['kind']} | {t['n_ok']}/{t['n_designs']} | {_fmt(t['wall_s'])} | "
                     f"{_fmt(t['newton'])} | {_fmt(t['peak_mb'])} | {_pct(t['max_rel_error'])} | "
                     f"{_pct(t['mean_rel_error'])} | {'yes' if t['pareto'] else ''} |")
    lines += ["", "## Per design (tradeoff.csv)", "",
              "| design | setting | status | wall s | process s | Newton | increments | cutbacks | peak MB | nodes | "
              "max error | mean error | max error mm |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['design']} | `{r['setting']}` | {r['status']} | {_fmt(r['wall_s'])} | "
                     f"{_fmt(r.get('process_s'))} | {_fmt(r.get('newton'))} | {_fmt(r.get('increments_taken'))} | "
                     f"{_fmt(r.get('cutbacks'))} | {_fmt(r.get('peak_mb'))} | {_fmt(r.get('nodes'))} | "
                     f"{_pct(r['max_rel_error'])} | {_pct(r['mean_rel_error'])} | {_fmt(r['max_error_mm'])} |")
    failed = [r for r in rows if r["status"] != "ok"]
    if failed:
        lines += ["", "## Failures", ""] + [f"- {r['design']} `{r['setting']}`: {r['status']}: {r['reason']}"
                                             for r in failed]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--panel", default="reduced", choices=("reduced", "full"))
    ap.add_argument("--out", default="reports/tradeoff")
    ap.add_argument("--reference", default="fine", help="mesh preset of the reference run (conf/mesh/)")
    ap.add_argument("--checkpoints", default="", help="comma-separated learned-simulator checkpoints to roll out")
    ap.add_argument("--install", action="store_true", help=f"write the per-setting FEA table to {TABLE}")
    ap.add_argument("--table", default=str(TABLE), help="where --install writes the table")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per FEA run before it counts as failed")
    ap.add_argument("--dominated", type=float, default=1.5,
                    help="stop a run after this multiple of the fastest finished run of its design on a mesh at least "
                         "as fine (status 'dominated')")
    ap.add_argument("--note", default="", help="a line on the conditions (e.g. machine load) for summary and table")
    ap.add_argument("--list", action="store_true", help="print the planned runs and exit")
    ap.add_argument("--keep", action="store_true", help="keep the episode files (temporary directory)")
    ap.add_argument("--resume", action="store_true",
                    help="reuse the finished FEA runs of OUT/tradeoff.csv and run only the missing ones (a long panel "
                         "over several sittings, same machine); reference episodes are kept in OUT/episodes")
    args = ap.parse_args()
    designs, settings = panel(args.panel, args.reference)
    reference = settings[0]
    if args.list:
        for pd in designs:
            for s in settings:
                print(f"{pd.name}\t{s.name}\t{' '.join(s.overrides())}\tmpirun -n {s.ranks}")
        print(f"{len(designs) * len(settings)} FEA runs")
        return
    checkpoints = [Path(c) for c in args.checkpoints.split(",") if c.strip()]
    for c in checkpoints:
        if not c.exists():
            raise SystemExit(f"--checkpoints: {c} does not exist")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "episodes" if args.resume else Path(tempfile.mkdtemp(prefix="tradeoff_"))
    tmp.mkdir(parents=True, exist_ok=True)
    prior = {}  # (design, setting) -> row of an earlier sitting (--resume); learned rows are always recomputed
    if args.resume and (out / "tradeoff.csv").exists():
        prior = {(r["design"], r["setting"]): r for r in read_csv(out / "tradeoff.csv")
                 if r["kind"] == "fea" and r["status"] != "skipped"}
        print(f"resuming: {len(prior)} finished FEA runs in {out / 'tradeoff.csv'}", flush=True)
    load_before = "/".join(f"{x:.2f}" for x in os.getloadavg())
    t_start = time.perf_counter()
    rows, designs_info, refs = [], [], {}
    for pd in designs:
        design = pd.draw()
        size = design.size
        m = design.meta
        designs_info.append({"name": pd.name, "grid": pd.grid, "index": pd.index, "size": size,
                             "family": f"{m['family']}/{m['shape']}", "actuators": m["actuators"],
                             "joints": f"{m['grid']['nx']}x{m['grid']['ny']}"})
        design_file = tmp / f"{pd.name}.json"
        design.save(design_file)
        done: list[tuple[Setting, float]] = []  # this design's finished runs and their process times
        for s in settings:
            if s != reference and refs.get(pd.name) is None:
                rows.append({**fea_row(pd, design, s, {"status": "skipped"}), "reason": "the reference run failed"})
                continue
            ep_file = tmp / f"{pd.name}__{s.name.replace('/', '_')}.h5"
            old = prior.get((pd.name, s.name))
            if old is not None and (s != reference or ep_file.exists()):  # finished in an earlier sitting
                from data_schema.episode import read_episode

                if s == reference:
                    refs[pd.name] = read_episode(ep_file)
                if old["status"] == "ok" and math.isfinite(old["process_s"]):
                    done.append((s, old["process_s"]))
                rows.append(old)
                continue
            cap = time_cap(s, done, args.dominated)
            timeout = args.timeout if cap is None else min(args.timeout, cap[0])
            res = run_solve(design_file, ep_file, s.overrides(), ranks=s.ranks, timeout=timeout)
            if res["status"] == "error":  # not a divergence: a crash, once retried (e.g. a kernel-cache race)
                print(json.dumps({"design": pd.name, "setting": s.name, "error, retrying": res["reason"]}), flush=True)
                res = run_solve(design_file, ep_file, s.overrides(), ranks=s.ranks, timeout=timeout)
                res["reason"] = ("retried once; " + str(res.get("reason") or "")).rstrip("; ")
            ep = res.pop("episode", None)
            if res["status"] == "timeout" and cap is not None and timeout < args.timeout:
                res.update(status="dominated", reason=f"stopped after {timeout:.0f} s = {args.dominated:g} x the "
                                                      f"{cap[1].name} run (a mesh at least as fine)")
            if ep is not None:
                done.append((s, res["process_s"]))
            row = fea_row(pd, design, s, res)
            if s == reference:
                refs[pd.name] = ep
            ref = refs.get(pd.name)
            if ep is not None and ref is not None:
                mx, mean = episode_error(ep, ref, size)
                row.update(max_rel_error=mx, mean_rel_error=mean, max_error_mm=mx * size)
            elif ep is not None:
                row["reason"] = "reference run failed: no error"
            rows.append(row)
            write_csv(out / "tradeoff.csv", rows)  # partial results survive an interrupted panel
            print(json.dumps({k: row[k] for k in ("design", "setting", "status", "wall_s", "newton", "peak_mb",
                                                  "max_rel_error", "reason")}), flush=True)
            if ep is not None and s != reference and not args.keep:
                ep_file.unlink(missing_ok=True)
    if checkpoints:
        from learn.checkpoint import load_model

        for c in checkpoints:
            model = load_model(c)
            for pd in designs:
                ref = refs.get(pd.name)
                if ref is None:
                    continue
                rows.append(learned_row(model, ref, learned_name(c), pd.name, float(ref.design_size)))
                print(json.dumps({k: rows[-1][k] for k in ("design", "setting", "status", "wall_s", "max_rel_error")}),
                      flush=True)
        learned_note = ", ".join(f"`{c}`" for c in checkpoints) + (
            " rolled out from frame 0 of each reference episode; error on the joint corner points rebuilt from "
            "the joint features, against the same reference corner nodes")
    else:
        learned_note = "none given (--checkpoints / CHECKPOINTS=): no learned rows"
    wall_total = time.perf_counter() - t_start
    load_after = "/".join(f"{x:.2f}" for x in os.getloadavg())

    write_csv(out / "tradeoff.csv", rows)
    # per-setting figures over the designs whose reference run succeeded
    table = summarize([r for r in rows if refs.get(r["design"]) is not None], reference, args.reference)
    plot(table, out, reference)
    atomic.write_text(out / "summary.md", markdown(rows, table, designs_info, reference, args, wall_total, load_before,
                                             load_after, learned_note))
    fea_table = [t for t in table if t["kind"] == "fea"]
    if args.install and not any(math.isfinite(t["max_rel_error"]) and not t["reference"] for t in fea_table):
        print(f"not installed: no FEA setting measured on every design (see {out / 'summary.md'})")
    elif args.install:
        path = write_table(Path(args.table), fea_table, [
            "Measured FEA speed/accuracy table: fea_factory.tradeoff.pick reads it for solver.tolerance.",
            f"Written by: {' '.join([Path(sys.executable).name, *sys.argv])}",
            f"Date: {time.strftime('%Y-%m-%d %H:%M')}; machine: {machine()}; load average {load_before} before, "
            f"{load_after} after",
            f"Panel: {args.panel} ({', '.join(d['name'] for d in designs_info)}); reference {reference.name}",
            *([f"Note: {args.note}"] if args.note else []),
            "max_rel_error: worst over the designs of the max joint-corner error / design size; wall_s: mean solver "
            "wall time; reference = 1: on the reference mesh (error is a lower bound, never picked)"])
        print(f"installed {path}")
    if not args.keep and not args.resume:
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        print(f"episodes kept in {tmp}")
    print((out / "summary.md").read_text())


if __name__ == "__main__":
    main()
