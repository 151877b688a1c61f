"""Where held-out errors sit, from learn.evaluate reports: by actuator kind and by design size, and what two validity
rules flag. `.venv/bin/python scripts/error_breakdown.py reports/a/102 [reports/b/102 ...] [--train-sizes DATA_DIR
--split conf/held_out/ds_default.yaml --train-designs 348] [--out reports/breakdown.md]`.

- kind: per report and pooled, the designs (all up, all down, mixed) and how many are worse than --bad (10 % of the
  design size: the validity calibration's flag_error_rel);
- size: the mixed designs' median and worst error per design-size bin (mm), beside how many training designs fall
  in each bin (with --train-sizes: the first --train-designs episodes by name that the split file does not hold out,
  as learn.train's train_designs takes them);
- rules: bad answers caught and good ones flagged by `out-of-range share > --max-out-of-range or unrolled indicator >
  T`, for T = --unrolled (the session-32 local threshold) and T = 0 (every one-kind design), as conf/validity judges;
- per model (with --quantiles): the out-of-range threshold each model would get from its own validation designs (the
  q-quantile of their shares; --split's `val`), measured on its other designs beside the fixed --max-out-of-range,
  every one-kind design flagged as conf/validity's local section does.
Session 36 (docs/learned_simulator.md) made its size table and its counts over four models with this; session 41 its
per-model table over eight.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from learn.compare import increasing_edges  # noqa: E402  (after the repository root is on the path)


def designs_of(report_dir: str) -> list[dict]:
    path = Path(report_dir)
    return json.loads((path / "report.json" if path.is_dir() else path).read_text())["designs"]


def training_sizes(data_dir: str, split_file: str, n: int | None) -> np.ndarray:
    """Design sizes (mm) of the first n training episodes by name: those the split file does not hold out."""
    from data_schema import read_episode
    from learn.features import extract

    split = yaml.safe_load(Path(split_file).read_text())
    held = set(split.get("val", [])) | set(split.get("test", []))
    paths = [p for p in sorted(Path(data_dir).glob("*.h5")) if p.name not in held][:n]
    if not paths:
        raise SystemExit(f"--train-sizes {data_dir}: no training episodes (*.h5 not held out by {split_file})")
    return np.array([extract(read_episode(p), name=p.name).design_size for p in paths])


def kind_table(reports: dict[str, list[dict]], bad: float) -> list[str]:
    lines = ["| report | kind | designs | worse than bad |", "|---|---|---|---|"]
    pooled: dict[str, list[int]] = {}
    for name, designs in reports.items():
        for kind in sorted({d["actuators"] for d in designs}):
            of = [d for d in designs if d["actuators"] == kind]
            n_bad = sum(d["max_rel_error"] > bad for d in of)
            lines.append(f"| {name} | {kind} | {len(of)} | {n_bad} |")
            pooled.setdefault(kind, [0, 0])
            pooled[kind][0] += len(of)
            pooled[kind][1] += n_bad
    lines += [f"| pooled | {k} | {n} | {b} |" for k, (n, b) in sorted(pooled.items())]
    return lines


def size_table(designs: list[dict], bins: list[float], train: np.ndarray | None) -> list[str]:
    lines = ["| design size (mm) | training designs | mixed held-out designs | median | worst |", "|---|---|---|---|---|"]
    mixed = [d for d in designs if d["actuators"] == "mixed"]
    for lo, hi in zip(bins[:-1], bins[1:]):
        e = np.array([d["max_rel_error"] for d in mixed if lo <= d["design_size_mm"] < hi])
        n_train = "-" if train is None else str(int(((train >= lo) & (train < hi)).sum()))
        stats = f"{100 * np.median(e):.2f} % | {100 * e.max():.2f} %" if len(e) else "- | -"
        lines.append(f"| {lo:g}-{hi:g} | {n_train} | {len(e)} | {stats} |")
    return lines


def flag_counts(flagged: np.ndarray, is_bad: np.ndarray) -> str:
    """'caught of bad | false of good | Youden's J' cells."""
    caught, false = int((flagged & is_bad).sum()), int((flagged & ~is_bad).sum())
    j = caught / max(is_bad.sum(), 1) - false / max((~is_bad).sum(), 1)
    return f"{caught} of {int(is_bad.sum())} | {false} of {int((~is_bad).sum())} | {j:.2f}"


def rule_table(reports: dict[str, list[dict]], bad: float, max_oor: float, unrolled: float) -> list[str]:
    lines = ["| rule | bad flagged | good flagged | Youden's J |", "|---|---|---|---|"]
    designs = [d for ds in reports.values() for d in ds]
    errors = np.array([d["max_rel_error"] for d in designs])
    oor = np.array([d["validity"]["out_of_range_fraction"] for d in designs])
    roll = np.array([d["validity"]["unrolled_one_kind"] for d in designs])
    is_bad = errors > bad
    for t in (unrolled, 0.0):
        flagged = (oor > max_oor) | (roll > t)
        lines.append(f"| out of range > {max_oor:g} or unrolled > {t:g} | {flag_counts(flagged, is_bad)} |")
    return lines


def per_model_table(reports: dict[str, list[dict]], val: set[str], quantiles: list[float], bad: float,
                    max_oor: float) -> list[str]:
    """Per report: the fixed out-of-range threshold against the q-quantiles of the shares of the model's own
    validation designs (those named in `val`), each measured on the report's other designs."""
    lines = ["| report | threshold | value | bad flagged | good flagged | Youden's J |", "|---|---|---|---|---|---|"]
    for name, designs in reports.items():
        in_val = np.array([d.get("name") in val for d in designs])
        if not in_val.any() or in_val.all():
            lines.append(f"| {name} | - | - | - | - | no split into validation and other designs |")
            continue
        oor = np.array([d["validity"]["out_of_range_fraction"] for d in designs])
        one_kind = np.array([d["validity"]["unrolled_one_kind"] > 0 for d in designs])
        is_bad = np.array([d["max_rel_error"] > bad for d in designs])[~in_val]
        for label, t in [("fixed", max_oor)] + [(f"validation q{q:g}", float(np.quantile(oor[in_val], q)))
                                                for q in quantiles]:
            flagged = ((oor > t) | one_kind)[~in_val]
            lines.append(f"| {name} | {label} | {t:.3f} | {flag_counts(flagged, is_bad)} |")
    return lines


def numbers(option: str, text: str) -> list[float]:
    """A comma-separated option as floats, or a clear error naming it."""
    try:
        return [float(x) for x in text.split(",")]
    except ValueError:
        raise SystemExit(f"{option}={text}: give numbers, comma-separated") from None


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("reports", nargs="+", help="learn.evaluate out_dirs (or their report.json); the first gets the "
                   "size table")
    p.add_argument("--bad", type=float, default=0.10, help="a design is bad above this max error / design size")
    p.add_argument("--bins", default="0,150,175,200,225,1000", help="design-size bin edges, mm, comma-separated")
    p.add_argument("--train-sizes", metavar="DATA_DIR", help="count training designs per size bin from this data")
    p.add_argument("--split", default="conf/held_out/ds_default.yaml", help="the split file of --train-sizes")
    p.add_argument("--train-designs", type=int, help="the first N training designs (learn.train's train_designs)")
    local = yaml.safe_load((ROOT / "conf" / "validity" / "default.yaml").read_text())["local"]
    p.add_argument("--max-out-of-range", type=float, default=local["max_out_of_range"],
                   help="default: conf/validity/default.yaml local: max_out_of_range")
    p.add_argument("--unrolled", type=float, default=0.867, help="the unrolled threshold to compare with 0")
    p.add_argument("--quantiles", help="per-model out-of-range thresholds from the validation designs' shares at "
                   "these quantiles, comma-separated in (0, 1), e.g. 0.5,0.67,0.8 (the validation designs: --split's val)")
    p.add_argument("--out", help="also write the tables here (markdown)")
    a = p.parse_args()
    if not 0 < a.bad < 1:
        raise SystemExit(f"--bad={a.bad}: allowed is a fraction of the design size in (0, 1)")
    try:
        bins = increasing_edges(numbers("--bins", a.bins), f"--bins={a.bins}")
    except ValueError as e:
        raise SystemExit(str(e)) from None
    quantiles = numbers("--quantiles", a.quantiles) if a.quantiles else []
    if any(not 0 < q < 1 for q in quantiles):
        raise SystemExit(f"--quantiles={a.quantiles}: allowed are fractions in (0, 1), comma-separated")
    reports = {r: designs_of(r) for r in a.reports}
    train = training_sizes(a.train_sizes, a.split, a.train_designs) if a.train_sizes else None
    text = "\n".join([f"# Error breakdown (bad: max error > {100 * a.bad:g} % of the design size)", "",
                      "## By actuator kind", "", *kind_table(reports, a.bad), "",
                      f"## Mixed designs by size ({a.reports[0]})", "", *size_table(reports[a.reports[0]], bins, train),
                      "", "## Validity rules over all reports", "",
                      *rule_table(reports, a.bad, a.max_out_of_range, a.unrolled), ""])
    if quantiles:
        val = set(yaml.safe_load(Path(a.split).read_text()).get("val", []))
        text += "\n".join(["", "## Out-of-range threshold per model (one-kind designs flagged; measured on the "
                            "designs outside validation)", "",
                            *per_model_table(reports, val, quantiles, a.bad, a.max_out_of_range), ""])
    print(text)
    if a.out:
        from data_schema import atomic
        atomic.write_text(Path(a.out), text)


if __name__ == "__main__":
    main()
