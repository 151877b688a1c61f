"""Calibrate the validity check's thresholds against FEA: `.venv/bin/python -m learn.validity_calibration
'reports=[reports/a]' ['check=[reports/b]'] out_dir=reports/validity_calibration` (conf/validity_calibration.yaml).

A learn.evaluate report holds, per held-out design, what the check reads (the rollout's largest face dislocation /
design size, the largest share of blocks outside the training feature range, an ensemble's spread) and the max error
the FEA says the answer has. A design is bad when that error exceeds `error_rel` (by default the flag_error_rel the
reports were measured with). For each indicator alone, and for those that judge every single model together
(the check flags when any exceeds its threshold), the thresholds are chosen to maximise Youden's J = the share of
bad designs flagged - the share of good designs flagged (ties: the fewer flags). The `check` reports, of other models
or other designs, measure the chosen thresholds where they were not fitted.

Writes calibration.json, calibration.md (a table per rule and the lines for conf/validity/default.yaml: at its top
level for a model.frame=global model, under its frame's section, e.g. `local:`, for a rotated-frame one) and
calibration.png (each indicator against the error, the thresholds drawn). Reports of one frame only.
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
from learn.evaluate import (_pct, finite_or_null, flag_error_rel_checked, flag_outcome, rank_correlation,
                            validity_indicators)
from learn.validity import judging_frame

log = logging.getLogger(__name__)
# the indicators that judge every single model's rollout, and their thresholds' names in conf/validity/default.yaml
CONF_KEYS = {"max_dislocation_rel": "max_dislocation_rel", "out_of_range_fraction": "max_out_of_range",
             "unrolled_one_kind": "max_unrolled_one_kind"}
MAX_CANDIDATES = 40  # thresholds tried per indicator in a joint rule (quantiles when more values were observed)


def pooled(reports: list[dict], what: str) -> tuple[list[dict], float | None]:
    """The designs of `reports` (all evaluated with one range_margin, so their out-of-range shares mean the same) and
    the flag_error_rel they were measured with (None if they do not say or disagree)."""
    if not reports:
        raise ValueError(f"{what}: give at least one learn.evaluate report (an out_dir or its report.json)")
    margins = {r.get("validity_thresholds", {}).get("range_margin") for r in reports}
    if len(margins) > 1:
        raise ValueError(f"{what}: reports evaluated with different validity.range_margin {sorted(map(str, margins))}; "
                         "their out-of-range shares are not comparable")
    flags = {r.get("validity_measured", {}).get("flag_error_rel") for r in reports}
    return [d for r in reports for d in r["designs"]], flags.pop() if len(flags) == 1 else None


def candidates(values: np.ndarray, at_most: int | None = None) -> np.ndarray:
    """Thresholds worth trying: flag above each observed value (or `at_most` of them at even quantiles), or never
    (inf)."""
    seen = np.unique(values[np.isfinite(values)])
    if at_most is not None and len(seen) > at_most:
        seen = np.unique(np.quantile(seen, np.linspace(0.0, 1.0, at_most), method="nearest"))
    return np.append(seen, np.inf)


def best_thresholds(values: list[np.ndarray], errors: np.ndarray, error_rel: float) -> tuple[list[float], dict]:
    """The thresholds (one per indicator; a design is flagged when any indicator exceeds its threshold) that maximise
    Youden's J over a grid of the observed values; ties go to the fewest flags, then to the larger thresholds (an
    indicator that adds nothing is left at inf: never flags)."""
    bad = errors > error_rel
    n_bad, n_good = max(int(bad.sum()), 1), max(int((~bad).sum()), 1)
    at_most = None if len(values) == 1 else MAX_CANDIDATES
    grids = np.meshgrid(*(candidates(v, at_most) for v in values), indexing="ij")
    taus = np.stack([g.ravel() for g in grids], axis=1)  # [T, k]
    flagged = (np.stack(values, axis=1)[None] > taus[:, None]).any(-1)  # [T, N]
    j = (flagged & bad).sum(1) / n_bad - (flagged & ~bad).sum(1) / n_good
    larger = np.argsort(np.argsort(-taus, axis=0), axis=0).sum(1)  # rank sum: small where the thresholds are large
    best = np.lexsort((larger, flagged.sum(1), -j))[0]
    return taus[best].tolist(), flag_outcome(errors, flagged[best], error_rel)


def calibrate(reports: list[dict], error_rel: float | None = None, check: list[dict] | None = None) -> dict:
    """Thresholds per rule (each indicator alone, and the single-model ones of CONF_KEYS together) fitted on
    `reports`, measured on `check` as well when given."""
    designs, measured_at = pooled(reports, "reports")
    if error_rel is None and measured_at is None:
        raise ValueError("error_rel: the reports do not say which flag_error_rel they were measured with; give one")
    error_rel = flag_error_rel_checked(measured_at if error_rel is None else error_rel, "error_rel")
    errors = np.array([d["max_rel_error"] for d in designs], dtype=np.float64)
    values = validity_indicators(designs)
    joint = tuple(k for k in CONF_KEYS if k in values)  # flagged when any of them exceeds its threshold
    rules = [(k,) for k in values] + ([joint] if len(joint) > 1 else [])
    others = pooled(check, "check")[0] if check else None
    other_values = validity_indicators(others) if others else {}
    out = {"error_rel": error_rel, "n_designs": len(designs), "n_bad": int((errors > error_rel).sum()),
           "frame": same_frame(reports + (check or [])),
           "range_margin": reports[0].get("validity_thresholds", {}).get("range_margin"),
           "spearman": {k: rank_correlation(v, errors) for k, v in values.items()}, "rules": []}
    for keys in rules:
        thresholds, fitted = best_thresholds([values[k] for k in keys], errors, error_rel)
        rule = {"indicators": list(keys), "thresholds": thresholds, "fitted": fitted}
        if all(k in other_values for k in keys):
            other_errors = np.array([d["max_rel_error"] for d in others], dtype=np.float64)
            flagged = np.stack([other_values[k] > t for k, t in zip(keys, thresholds)], axis=1).any(1)
            rule["check"] = flag_outcome(other_errors, flagged, error_rel)
        out["rules"].append(rule)
    return out


def model_frame(model: dict) -> str:
    """The section of conf/validity/default.yaml whose thresholds judge the model a report describes (its `model`
    args; an ensemble's `member_args` when they differ): learn.validity.judging_frame of its members' frames."""
    return judging_frame(a.get("frame", "global") for a in model.get("member_args", [model]))


def same_frame(reports: list[dict]) -> str:
    """The one model_frame of every report (thresholds fitted to one frame's rollouts judge only that frame's)."""
    frames = {model_frame(r.get("model", {})) for r in reports}
    if len(frames) > 1:
        raise ValueError(f"reports: models of different frames {sorted(frames)} (their thresholds differ, "
                         "conf/validity/default.yaml); calibrate each frame apart")
    return frames.pop()


def _share(o: dict) -> str:
    return (f"{o['caught']} of {o['n_bad']} bad flagged, {o['false_flags']} of {o['n'] - o['n_bad']} good flagged; "
            f"passed {_pct(o['passed']['median'])} median / {_pct(o['passed']['p95'])} p95, "
            f"flagged {_pct(o['flagged']['median'])} median")


def markdown(result: dict) -> str:
    lines = [f"# Validity thresholds against FEA: a design is bad when its max error > {_pct(result['error_rel'])} "
             f"of its size ({result['n_bad']} of {result['n_designs']} designs)", "",
             "Spearman of each indicator with the max error: "
             + ", ".join(f"{k} {v:.2f}" for k, v in result["spearman"].items()), "",
             "| rule | thresholds | fitted: J | fitted | check: J | check |", "|---|---|---|---|---|---|"]
    for rule in result["rules"]:
        fitted, check = rule["fitted"], rule.get("check")
        thresholds = ", ".join("never" if t is None or not np.isfinite(t) else f"{t:.4g}" for t in rule["thresholds"])
        lines.append(f"| {' or '.join(rule['indicators'])} | {thresholds} | {fitted['youden_j']:.2f} | "
                     f"{_share(fitted)} | {'-' if check is None else format(check['youden_j'], '.2f')} | "
                     f"{'-' if check is None else _share(check)} |")
    joint = next((r for r in result["rules"] if len(r["indicators"]) > 1), None)
    if joint is not None:
        frame = result.get("frame", "global")
        where, indent = ("", "") if frame == "global" else (f", under `{frame}:` (a model.frame={frame} model)", "  ")
        lines += ["", f"For conf/validity/default.yaml{where} (range_margin {result['range_margin']}; 1.0 = never "
                  "flags):", "", "```yaml", *([f"{frame}:"] if indent else []),
                  *(f"{indent}{CONF_KEYS[k]}: {1.0 if t is None else min(t, 1.0):.4g}"
                    for k, t in zip(joint["indicators"], joint["thresholds"])), "```"]
    return "\n".join(lines) + "\n"


def plot(designs: list[dict], result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    singles = [r for r in result["rules"] if len(r["indicators"]) == 1]
    fig, axes = plt.subplots(1, len(singles), figsize=(4.5 * len(singles), 4), squeeze=False)
    errors, values = np.array([d["max_rel_error"] for d in designs]), validity_indicators(designs)
    for ax, rule in zip(axes[0], singles):
        key = rule["indicators"][0]
        ax.scatter(values[key], 100 * errors, s=12, alpha=0.7)
        ax.axhline(100 * result["error_rel"], color="k", lw=0.8, ls="--", label="bad above")
        if rule["thresholds"][0] is not None and np.isfinite(rule["thresholds"][0]):
            ax.axvline(rule["thresholds"][0], color="r", lw=0.8, label="flag right of")
        ax.set_xlabel(key)
        ax.set_ylabel("max error / design size (%)")
        ax.set_title(f"Spearman {result['spearman'][key]:.2f}, J {rule['fitted']['youden_j']:.2f}")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


@hydra.main(version_base="1.3", config_path="../conf", config_name="validity_calibration")
def main(cfg: DictConfig) -> None:
    reports = [read_report(p) for p in cfg.reports]
    check = [read_report(p) for p in cfg.check] if cfg.check else None
    result = calibrate(reports, cfg.error_rel, check)
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic.write_text(out / "calibration.json", json.dumps(finite_or_null(result), indent=1, allow_nan=False))
    atomic.write_text(out / "calibration.md", markdown(result))
    plot(pooled(reports, "reports")[0], result, out / "calibration.png")
    log.info("\n%s", markdown(result))


if __name__ == "__main__":
    main()
