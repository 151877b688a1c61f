"""The measured speed/accuracy trade of the FEA settings, and `solver.tolerance`: the cheapest setting that meets it.

A *setting* is one combination of the knobs that buy speed with accuracy: mesh preset (conf/mesh/), load-increment
mode (INCREMENT_MODES), linear solver (direct | iterative) and MPI ranks. `scripts/tradeoff.py` (`make tradeoff`)
measures every setting of a panel of designs against the finest FEA reference of the same run; with `--install` it
writes one row per setting into TABLE (conf/solver/tradeoff_table.csv, committed: the one source of truth).

    python -m fea_factory.solve design=FILE out=FILE.h5 solver.tolerance=0.01     # or solver.tolerance=1%
    python -m fea_factory.generate n=8 out=DIR solver.tolerance=2%

replaces the mesh preset, linear solver and increment mode of the config by those of the cheapest measured
setting whose worst max corner-node error over the panel, divided by the design size, is <= the tolerance
(cost = mean solver wall time over the panel). Rows run with the episode's rank count are preferred when one of
them meets the tolerance; the pick is recorded in the episode's stored config under solver.tolerance_pick. Rows on
the reference mesh itself only measure solver/rank/increment differences, not discretisation error (their error
is a lower bound), so they are never picked. Everything here is pure (no FEA) except reading the table file.
"""
from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_schema import atomic

ROOT = Path(__file__).resolve().parent.parent
TABLE = ROOT / "conf" / "solver" / "tradeoff_table.csv"

# load-increment modes: conf/solver overrides; every mode saves the same 11 frames (t = 0, 0.1, ..., 1)
INCREMENT_MODES: dict[str, dict[str, object]] = {
    "adaptive": {"adaptive": True, "increments": 100, "save_every": 10},  # conf/solver/default.yaml
    "fixed10": {"adaptive": False, "increments": 10, "save_every": 1},
    "fixed20": {"adaptive": False, "increments": 20, "save_every": 2},
}
LINEAR_SOLVERS = ("direct", "iterative")
TABLE_COLUMNS = ("setting", "mesh", "increments", "linear_solver", "ranks", "n_designs", "n_ok", "wall_s",
                 "max_rel_error", "mean_rel_error", "newton", "peak_mb", "reference")


class TradeoffError(ValueError):
    """solver.tolerance cannot be honoured (invalid value, no table, or no measured setting meets it)."""


@dataclass(frozen=True)
class Setting:
    """One FEA setting of the panel."""

    mesh: str = "default"
    increments: str = "adaptive"
    linear_solver: str = "direct"
    ranks: int = 1

    def __post_init__(self) -> None:
        if self.increments not in INCREMENT_MODES:
            raise ValueError(f"increments mode {self.increments!r}: must be one of {sorted(INCREMENT_MODES)}")
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(f"linear solver {self.linear_solver!r}: must be one of {LINEAR_SOLVERS}")
        if int(self.ranks) < 1:
            raise ValueError(f"ranks = {self.ranks}: must be >= 1")

    @property
    def name(self) -> str:
        return f"{self.mesh}/{self.increments}/{self.linear_solver}/n{self.ranks}"

    def overrides(self) -> list[str]:
        """Command-line overrides of fea_factory.solve (the ranks go to mpirun -n)."""
        solver = {**INCREMENT_MODES[self.increments], "linear_solver": self.linear_solver}
        return [f"mesh={self.mesh}"] + [f"solver.{k}={str(v).lower() if isinstance(v, bool) else v}"
                                        for k, v in solver.items()]


# ------------------------------------------------------------------------------------------------ front
def pareto_front(cost: Iterable[float], error: Iterable[float]) -> np.ndarray:
    """Boolean mask of the points no other point beats in both cost and error (both minimised).
    Of identical points only the first is on the front; NaN points never are."""
    c, e = np.asarray(list(cost), float), np.asarray(list(error), float)
    mask = np.zeros(len(c), bool)
    ok = np.flatnonzero(np.isfinite(c) & np.isfinite(e))
    best = math.inf
    for i in ok[np.lexsort((ok, e[ok], c[ok]))]:  # by cost, then error, then input order
        if e[i] < best:
            mask[i], best = True, e[i]
    return mask


# ------------------------------------------------------------------------------------------------ table
def aggregate(rows: Iterable[Mapping], reference_mesh: str) -> list[dict]:
    """Per-design measurements (keys: setting, mesh, increments, linear_solver, ranks, status, wall_s,
    max_rel_error, mean_rel_error, newton, peak_mb) -> one table row per setting: worst max error and mean of the
    mean errors over the designs, mean wall time and Newton iterations, largest memory peak. A setting that failed
    (or has no error) on any design gets max_rel_error = inf, so it is never picked."""
    by: dict[str, list[Mapping]] = {}
    for r in rows:
        by.setdefault(r["setting"], []).append(r)
    out = []
    for name, rs in by.items():
        ok = [r for r in rs if r.get("status") == "ok" and _finite(r.get("max_rel_error"))]
        all_ok = len(ok) == len(rs)
        r0 = rs[0]
        out.append({
            "setting": name, "mesh": r0["mesh"], "increments": r0["increments"], "linear_solver": r0["linear_solver"],
            "ranks": int(r0["ranks"]), "n_designs": len(rs), "n_ok": len(ok),
            "wall_s": float(np.mean([r["wall_s"] for r in ok])) if ok else math.inf,
            "max_rel_error": max(float(r["max_rel_error"]) for r in ok) if all_ok else math.inf,
            "mean_rel_error": float(np.mean([r["mean_rel_error"] for r in ok])) if all_ok else math.inf,
            "newton": float(np.mean([r["newton"] for r in ok])) if ok else math.nan,
            "peak_mb": max(float(r.get("peak_mb") or 0.0) for r in rs),
            "reference": int(r0["mesh"] == reference_mesh)})
    return out


def _finite(x) -> bool:
    try:
        return math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def write_table(path: Path, rows: Iterable[Mapping], comments: Iterable[str] = ()) -> Path:
    """CSV with '# ' comment lines first (provenance), then TABLE_COLUMNS."""
    formatted = ({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()} for r in rows)
    return atomic.write_csv(path, formatted, TABLE_COLUMNS, comments)


def read_table(path: Path = TABLE) -> list[dict]:
    path = Path(path)
    if not path.exists():
        raise TradeoffError(f"solver.tolerance needs the measured table {path}, which does not exist; write it with "
                            f"`make tradeoff INSTALL=1` (scripts/tradeoff.py --install)")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(line for line in f if not line.startswith("#")))
    missing = set(TABLE_COLUMNS) - set(rows[0] if rows else TABLE_COLUMNS)
    if not rows or missing:
        raise TradeoffError(f"{path}: not a trade-off table (no rows, or missing columns {sorted(missing)})")
    for r in rows:
        for k in ("wall_s", "max_rel_error", "mean_rel_error", "newton", "peak_mb"):
            r[k] = float(r[k]) if r[k] not in ("", None) else math.nan
        for k in ("ranks", "n_designs", "n_ok", "reference"):
            r[k] = int(r[k])
    return rows


# ------------------------------------------------------------------------------------------------ pick
def parse_tolerance(value) -> float:
    """solver.tolerance as a fraction of the design size: 0.01 or "1%"; must lie in (0, 1)."""
    msg = (f"solver.tolerance = {value!r}: must be a max position error relative to the design size in (0, 1), "
           f"e.g. solver.tolerance=0.01 or solver.tolerance=1%")
    if isinstance(value, bool):
        raise TradeoffError(msg)
    try:
        tol = float(value[:-1]) / 100 if isinstance(value, str) and value.strip().endswith("%") else float(value)
    except (TypeError, ValueError):
        raise TradeoffError(msg) from None
    if not (math.isfinite(tol) and 0.0 < tol < 1.0):
        raise TradeoffError(msg)
    return tol


def pick(table: list[Mapping], tolerance: float, ranks: int | None = None, source: str = "the table") -> dict:
    """The cheapest measured setting (least wall_s; ties: smaller error, then name) whose max_rel_error <=
    tolerance, among the rows run with `ranks` ranks if any of them meets it, else among all rows. Rows on the
    reference mesh are excluded (error not measured). Raises TradeoffError naming solver.tolerance and the
    achievable range."""
    tol = parse_tolerance(tolerance)
    rows = [r for r in table if not r["reference"] and _finite(r["max_rel_error"]) and _finite(r["wall_s"])]
    if not rows:
        raise TradeoffError(f"solver.tolerance = {tol:g}: {source} has no measured setting (every one failed or "
                            f"is the reference); re-measure with `make tradeoff INSTALL=1`")
    meets = [r for r in rows if r["max_rel_error"] <= tol]
    if ranks is not None and any(int(r["ranks"]) == int(ranks) for r in meets):
        meets = [r for r in meets if int(r["ranks"]) == int(ranks)]
    if not meets:
        best = min(rows, key=lambda r: (r["max_rel_error"], r["wall_s"]))
        worst = max(r["max_rel_error"] for r in rows)
        raise TradeoffError(
            f"solver.tolerance = {tol:g}: no measured FEA setting in {source} meets it; the measured settings "
            f"reach max errors from {best['max_rel_error']:.3g} ({best['setting']}) to {worst:.3g}. Loosen "
            f"solver.tolerance to >= {best['max_rel_error']:.3g}, or choose mesh/solver explicitly (e.g. the "
            f"reference mesh, whose own error is not measured) without solver.tolerance")
    return dict(min(meets, key=lambda r: (r["wall_s"], r["max_rel_error"], r["setting"])))


def setting_of(row: Mapping) -> Setting:
    return Setting(str(row["mesh"]), str(row["increments"]), str(row["linear_solver"]), int(row["ranks"]))


def apply_tolerance(cfg, ranks: int = 1, table: Path | None = None) -> dict | None:
    """If cfg.solver.tolerance is set: pick from the table (`table`, else cfg.solver.tolerance_table, else TABLE),
    overwrite cfg.mesh (conf/mesh/<preset>.yaml) and the solver's linear_solver/adaptive/increments/save_every in
    place, record the pick in cfg.solver.tolerance_pick and return it. None (cfg untouched) without a tolerance."""
    from omegaconf import OmegaConf, open_dict

    value = cfg.solver.get("tolerance") if "solver" in cfg else None
    if value is None:
        return None
    tol = parse_tolerance(value)
    if table is None:  # +solver.tolerance_table=FILE (undeclared in conf: tests, or a table measured elsewhere)
        table = cfg.solver.get("tolerance_table") or TABLE
    path = Path(table)
    row = pick(read_table(path), tol, ranks=ranks, source=str(path.relative_to(ROOT) if path.is_relative_to(ROOT)
                                                              else path))
    s = setting_of(row)
    preset = ROOT / "conf" / "mesh" / f"{s.mesh}.yaml"
    if not preset.exists():
        raise TradeoffError(f"solver.tolerance = {tol:g}: picked setting {s.name} names mesh preset {s.mesh!r}, "
                            f"but {preset} does not exist")
    record = {"tolerance": tol, "setting": s.name, "measured_max_rel_error": float(row["max_rel_error"]),
              "measured_wall_s": float(row["wall_s"]), "measured_ranks": s.ranks, "table": str(path)}
    with open_dict(cfg):
        cfg.mesh = OmegaConf.load(preset)
        for k, v in {**INCREMENT_MODES[s.increments], "linear_solver": s.linear_solver}.items():
            cfg.solver[k] = v
        cfg.solver.tolerance_pick = record
    return record
