"""Paired comparison of learned-simulator reports over the same designs: `.venv/bin/python -m learn.compare
'reports=[reports/a,reports/b,...]' out_dir=reports/a_vs_b` (conf/compare.yaml).

With ~100 held-out designs a median moves by a few tenths of a point between seeds, so two models are compared
design by design, not by their medians alone: for every report after the first (the base), on how many designs its
max error / design size is lower than the base's, and the median over designs of its error divided by the base's
(x0.77: a typical design's error falls by 23 %). The reports are learn.evaluate or learn.combine outputs; they must
hold the same designs, named by data set and episode. Writes compare.json, compare.md and compare.png (each design's
error against the base's, log-log).

With `sizes` (one number per report, e.g. its training designs) the reports are points of a scaling curve: each
design's error is fitted as a N^-b (least squares in log-log over the reports), and the table gives the median of the
per-design exponents b, the exponents of the median and p95 errors, and the N at which the median would reach
`target` if the power law held (an extrapolation, stated as one); scaling.png draws median and p95 against N.

With `size_bins` (design-size edges, mm) the same comparison per bin of the designs' size (the base report's
design_size_mm): each report's median there, and against the base the designs better and the median ratio, so a
change that moves the error between small and large designs shows (session 41).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from data_schema import atomic
from learn.combine import read_report
from learn.evaluate import finite_or_null

log = logging.getLogger(__name__)


def design_errors(report: dict) -> dict[tuple[str, str], float]:
    """(data set, episode) -> max error / design size. learn.combine stores each design's data_dir; a single
    learn.evaluate report has one for all."""
    return {(str(d.get("data_dir", report["data_dir"])), d["name"]): float(d["max_rel_error"])
            for d in report["designs"]}


def paired(base: np.ndarray, other: np.ndarray) -> dict:
    """How `other` does against `base` on the same designs (arrays of max error / design size, aligned)."""
    return {"better_on": int((other < base).sum()), "worse_on": int((other > base).sum()),
            "median_ratio": float(np.median(other / base))}


def summary(errors: np.ndarray) -> dict:
    return {"n": int(len(errors)), "median": float(np.median(errors)), "p95": float(np.percentile(errors, 95)),
            "worst": float(errors.max()), "mean": float(errors.mean())}


def compare(reports: list[dict], labels: list[str]) -> dict:
    """One row per report: its error distribution, and for all but the first the paired comparison with the first."""
    if len(reports) < 2:
        raise ValueError(f"reports: {len(reports)} given; a comparison needs at least 2")
    if len(labels) != len(reports):
        raise ValueError(f"labels: {len(labels)} given for {len(reports)} reports")
    errs = [design_errors(r) for r in reports]
    keys = sorted(errs[0])
    for label, e in zip(labels[1:], errs[1:]):
        if set(e) != set(keys):
            only_base, only_this = sorted(set(keys) - set(e)), sorted(set(e) - set(keys))
            raise ValueError(f"reports: {label} holds other designs than {labels[0]} (missing {len(only_base)}: "
                             f"{only_base[:3]}; extra {len(only_this)}: {only_this[:3]}); compare reports over the "
                             "same designs")
    arrays = [np.array([e[k] for k in keys]) for e in errs]
    welded = [bool(r.get("welded", False)) for r in reports]  # one position per FEA node (learn.evaluate weld=true)
    rows = [{"label": labels[0], "welded": welded[0], **summary(arrays[0])}]
    rows += [{"label": lab, "welded": w, **summary(a), **paired(arrays[0], a)}
             for lab, w, a in zip(labels[1:], welded[1:], arrays[1:])]
    worst = [{"data_dir": keys[i][0], "name": keys[i][1], "errors": [float(a[i]) for a in arrays]}
             for i in np.argsort(-arrays[0])[:5]]
    return {"base": labels[0], "n_designs": len(keys), "rows": rows, "base_worst_designs": worst,
            "designs": [{"data_dir": k[0], "name": k[1]} for k in keys],
            "max_rel_error": [a.tolist() for a in arrays]}


def increasing_edges(edges: list[float], option: str) -> list[float]:
    """Design-size bin edges (mm) as given, or a ValueError naming the option: at least two, strictly increasing."""
    if len(edges) < 2 or any(hi <= lo for lo, hi in zip(edges[:-1], edges[1:])):
        raise ValueError(f"{option}: give at least two increasing edges in mm")
    return edges


def by_design_size(result: dict, reports: list[dict], edges: list[float]) -> list[dict]:
    """compare's rows again per design-size bin [lo, hi) (mm, the base report's design_size_mm of each design)."""
    increasing_edges(edges, f"size_bins={edges}")
    size_of = {(str(d.get("data_dir", reports[0]["data_dir"])), d["name"]): d.get("design_size_mm")
               for d in reports[0]["designs"]}
    keys = [(d["data_dir"], d["name"]) for d in result["designs"]]
    if any(size_of[k] is None for k in keys):
        raise ValueError("size_bins: the base report's designs carry no design_size_mm (re-run learn.evaluate)")
    size = np.array([size_of[k] for k in keys], dtype=float)
    arrays = [np.asarray(a) for a in result["max_rel_error"]]
    labels = [r["label"] for r in result["rows"]]
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (size >= lo) & (size < hi)
        rows = [] if not m.any() else [{"label": labels[0], "median": float(np.median(arrays[0][m]))}] + [
            {"label": lab, "median": float(np.median(a[m])), **paired(arrays[0][m], a[m])}
            for lab, a in zip(labels[1:], arrays[1:])]
        out.append({"lo": float(lo), "hi": float(hi), "n": int(m.sum()), "rows": rows})
    return out


def by_size_markdown(bins: list[dict]) -> str:
    lines = ["", "## By design size (mm): median, and against the base: better on, median ratio", "",
             "| size | designs | report | median | better than the base on | median ratio to the base |",
             "|---|---|---|---|---|---|"]
    for b in bins:
        for r in b["rows"]:
            vs = f"{r['better_on']} of {b['n']} | x{r['median_ratio']:.3f}" if "better_on" in r else "(base) | "
            lines.append(f"| {b['lo']:g}-{b['hi']:g} | {b['n']} | {r['label']} | {100 * r['median']:.2f} % | {vs} |")
        if not b["rows"]:
            lines.append(f"| {b['lo']:g}-{b['hi']:g} | 0 | - | - | - | - |")
    return "\n".join(lines) + "\n"


def power_law_exponent(sizes, errors) -> float:
    """b of errors ~ a sizes^-b, least squares in log-log (errors [..., len(sizes)]: one fit per leading index)."""
    x = np.log(np.asarray(sizes, dtype=np.float64))
    y = np.log(np.asarray(errors, dtype=np.float64))
    xc = x - x.mean()
    return -((y - y.mean(axis=-1, keepdims=True)) @ xc) / (xc @ xc)


def scaling(result: dict, sizes: list[float], target: float) -> dict:
    """The reports as a scaling curve over `sizes` (compare's result): per-design exponents and those of the median
    and p95, and the size at which the median would reach `target` by the median's power law."""
    if len(sizes) != len(result["rows"]):
        raise ValueError(f"sizes: {len(sizes)} given for {len(result['rows'])} reports (one per report)")
    if len(set(sizes)) < 2 or min(sizes) <= 0:
        raise ValueError(f"sizes={sizes}: need positive numbers, at least two different ones")
    if not 0 < target:
        raise ValueError(f"target={target}: must be a positive error (a fraction of the design size)")
    per_design = power_law_exponent(sizes, np.asarray(result["max_rel_error"]).T)  # [designs]
    out = {"sizes": [float(n) for n in sizes], "target": float(target),
           "per_design_exponent_median": float(np.median(per_design)),
           "per_design_exponent_quartiles": [float(q) for q in np.percentile(per_design, [25, 75])]}
    big = int(np.argmax(sizes))  # the extrapolation starts from the largest size measured
    for stat in ("median", "p95"):
        values = [r[stat] for r in result["rows"]]
        b = float(power_law_exponent(sizes, values))
        out[f"{stat}_exponent"] = b
        out[f"{stat}_at_target_size"] = (float(sizes[big] * (values[big] / target) ** (1.0 / b)) if b > 0
                                         else None)  # None: no fall with size, no size reaches the target
    return out


def scaling_markdown(sc: dict) -> str:
    n = lambda v: "never (no fall with size)" if v is None else f"~{v:,.0f}"  # noqa: E731
    return "\n".join([
        "", f"## Scaling with size ({', '.join(f'{v:g}' for v in sc['sizes'])}): error ~ N^-b", "",
        f"- per design: median b = {sc['per_design_exponent_median']:.2f} (quartiles "
        f"{sc['per_design_exponent_quartiles'][0]:.2f} to {sc['per_design_exponent_quartiles'][1]:.2f})",
        f"- median error: b = {sc['median_exponent']:.2f}; it would reach {100 * sc['target']:.2f} % at N "
        f"{n(sc['median_at_target_size'])}",
        f"- p95 error: b = {sc['p95_exponent']:.2f}; it would reach {100 * sc['target']:.2f} % at N "
        f"{n(sc['p95_at_target_size'])}",
        "- (the last two extrapolate a power law fitted over the sizes above: an estimate, not a measurement)", ""])


def plot_scaling(result: dict, path: Path) -> None:
    """Median and p95 of max error / design size against size, log-log, with the fitted power laws."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sc = result["scaling"]
    sizes = np.asarray(sc["sizes"])
    grid = np.geomspace(sizes.min(), sizes.max() * 2, 50)
    big = int(np.argmax(sizes))  # the fitted lines pass through the largest size's point, as scaling extrapolates
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for stat, colour in (("median", "C0"), ("p95", "C1")):
        values = np.array([100 * r[stat] for r in result["rows"]])
        ax.scatter(sizes, values, color=colour, label=f"{stat} (b = {sc[f'{stat}_exponent']:.2f})")
        ax.plot(grid, values[big] * (grid / sizes[big]) ** -sc[f"{stat}_exponent"], color=colour, lw=0.8, ls="--")
    ax.axhline(100 * sc["target"], color="k", lw=0.8, label=f"target {100 * sc['target']:.2f} %")
    ax.set(xscale="log", yscale="log", xlabel="size (training designs)", ylabel="max error / design size (%)",
           title=f"{result['n_designs']} held-out designs")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def markdown(result: dict) -> str:
    pct = lambda x: f"{100 * x:.2f} %"  # noqa: E731
    lines = [f"# {result['n_designs']} designs, max error / design size, each report against {result['base']}", "",
             "| report | median | p95 | worst | mean | better than the base on | median ratio to the base |",
             "|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        vs = (f"{r['better_on']} of {r['n']} (worse on {r['worse_on']}) | x{r['median_ratio']:.3f}"
              if "better_on" in r else "(base) | ")
        label = r["label"] + (" (welded)" if r.get("welded") else "")
        lines.append(f"| {label} | {pct(r['median'])} | {pct(r['p95'])} | {pct(r['worst'])} | {pct(r['mean'])} "
                     f"| {vs} |")
    lines += ["", "The base's worst designs:", "", "| design | " + " | ".join(r["label"] for r in result["rows"]) + " |",
              "|---|" + "---|" * len(result["rows"])]
    lines += [f"| {w['data_dir']}/{w['name']} | " + " | ".join(pct(e) for e in w["errors"]) + " |"
              for w in result["base_worst_designs"]]
    text = "\n".join(lines) + "\n"
    if "by_size" in result:
        text += by_size_markdown(result["by_size"])
    return text + scaling_markdown(result["scaling"]) if "scaling" in result else text


def plot(result: dict, path: Path) -> None:
    """Each design's error under every other report against the base's (log-log; below the diagonal: better)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    errors = [100 * np.asarray(e) for e in result["max_rel_error"]]
    fig, ax = plt.subplots(figsize=(6, 6))
    for row, e in zip(result["rows"][1:], errors[1:]):
        ax.scatter(errors[0], e, s=12, alpha=0.7, label=f"{row['label']} (x{row['median_ratio']:.2f})")
    lo, hi = min(e.min() for e in errors) * 0.8, max(e.max() for e in errors) * 1.25
    ax.plot([lo, hi], [lo, hi], color="k", lw=0.8)
    ax.set(xscale="log", yscale="log", xlim=(lo, hi), ylim=(lo, hi), xlabel=f"{result['base']}: max error / size (%)",
           ylabel="other report: max error / size (%)", title=f"{result['n_designs']} designs (below the line: better)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_outputs(out_dir: str | Path, stem: str, result: dict, to_markdown, to_plot=None) -> None:
    """stem.json, stem.md and (when to_plot is given) stem.png in out_dir, each written atomically; the table logged."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic.write_text(out_dir / f"{stem}.json", json.dumps(finite_or_null(result), indent=1, allow_nan=False))
    atomic.write_text(out_dir / f"{stem}.md", to_markdown(result))
    if to_plot is not None:
        to_plot(result, out_dir / f"{stem}.png")
    log.info("\n%s", to_markdown(result))


@hydra.main(version_base="1.3", config_path="../conf", config_name="compare")
def main(cfg: DictConfig) -> None:
    paths = [str(p) for p in cfg.reports]
    labels = [str(v) for v in cfg.labels] if cfg.labels else paths
    reports = [read_report(p) for p in paths]
    result = compare(reports, labels)
    if cfg.get("size_bins"):
        result["by_size"] = by_design_size(result, reports, [float(v) for v in cfg.size_bins])
    if cfg.get("sizes"):
        result["scaling"] = scaling(result, [float(v) for v in cfg.sizes], float(cfg.target))
    write_outputs(cfg.out_dir, "compare", result, markdown, plot if cfg.plots else None)
    if cfg.plots and "scaling" in result:
        plot_scaling(result, Path(cfg.out_dir) / "scaling.png")


if __name__ == "__main__":
    main()
