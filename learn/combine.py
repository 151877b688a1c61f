"""Pool learn.evaluate reports of one model over several data sets into one: `.venv/bin/python -m learn.combine
'reports=[reports/a,reports/b]' out_dir=reports/ab` (conf/combine.yaml).

The error distributions (median, p95, worst; overall and per design family) are recomputed over the union of the
reports' designs, which is what a median over two held-out sets means; timings and the FEA time are the
design-weighted means of the sources'. Every source must come from the same checkpoint with the same symmetry
averaging, and no design may appear twice. Writes report.json (learn.evaluate's schema plus `sources`) and report.md.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from data_schema import atomic
from learn.evaluate import design_statistics, finite_or_null, markdown

log = logging.getLogger(__name__)
WEIGHTED = ("rollout_ms_per_design", "rollout_ms_per_design_eager", "rollout_ms_per_design_batched",
            "fea_s_per_episode")
SAME = ("checkpoint", "model", "threads", "steps", "welded", "validity_thresholds", "rollout_backend")
ABSENT = {"welded": False, "rollout_backend": "torchscript"}  # what a report written before the key was added measured


def read_report(path: str | Path) -> dict:
    path = Path(path)
    path = path / "report.json" if path.is_dir() else path
    if not path.exists():
        raise FileNotFoundError(f"reports: {path} does not exist (a learn.evaluate out_dir or its report.json)")
    return json.loads(path.read_text())


def fea_load_mean(reports: list[dict]) -> float | None:
    """The design-weighted mean of the reports' FEA load per CPU, over those that recorded one (None if none did)."""
    known = [(r["fea_load_per_cpu_mean"], r["n_designs"]) for r in reports
             if r.get("fea_load_per_cpu_mean") is not None and np.isfinite(r["fea_load_per_cpu_mean"])]
    return float(np.average([v for v, _ in known], weights=[n for _, n in known])) if known else None


def combine(reports: list[dict]) -> dict:
    """One report over the union of the designs of `reports` (learn.evaluate report dicts)."""
    if len(reports) < 2:
        raise ValueError(f"reports: {len(reports)} given; pooling needs at least 2")
    for key in SAME:
        values = {json.dumps(r.get(key, ABSENT.get(key)), sort_keys=True) for r in reports}
        if len(values) > 1:
            raise ValueError(f"reports differ in {key!r} ({sorted(values)}): pool only one model's reports")
    designs = [{**d, "data_dir": r["data_dir"]} for r in reports for d in r["designs"]]
    keys = [(d["data_dir"], d["name"]) for d in designs]
    twice = sorted({k for k in keys if keys.count(k) > 1})
    if twice:
        raise ValueError(f"reports: designs appear more than once: {twice[:5]}")
    weights = np.array([r["n_designs"] for r in reports], dtype=float)
    mean = lambda key: float(np.average([np.nan if r.get(key) is None else r[key] for r in reports],  # noqa: E731
                                        weights=weights))
    flag = {r.get("validity_measured", {}).get("flag_error_rel") for r in reports}
    if len(flag) > 1:
        raise ValueError(f"reports differ in flag_error_rel ({sorted(map(str, flag))}): evaluate them with one value")
    out = {
        **design_statistics(designs, flag.pop()),
        **{key: mean(key) for key in WEIGHTED},
        "n_invalid": int(sum(not d["valid"] for d in designs)),
        **{key: reports[0].get(key, ABSENT.get(key)) for key in SAME},
        "split": " + ".join(f"{r['data_dir']}:{r['split']}" for r in reports),
        "data_dir": ", ".join(r["data_dir"] for r in reports),
        "n_parameters": reports[0].get("n_parameters"),
        "timing_busy": any(bool(r.get("timing_busy")) for r in reports),
        "load_average": max((r["load_average"] for r in reports if r.get("load_average") is not None), default=None),
        "fea_load_per_cpu_mean": fea_load_mean(reports),
        "cpus": reports[0].get("cpus"),
        "timing": "design-weighted means of the sources' timings (learn.evaluate: " + reports[0].get("timing", "") + ")",
        "sources": [{"data_dir": r["data_dir"], "split": r["split"], "n_designs": r["n_designs"],
                     "rollout_ms_per_design": r["rollout_ms_per_design"], "timing_busy": r.get("timing_busy")}
                    for r in reports],
        "designs": designs,
    }
    out["speedup"] = out["fea_s_per_episode"] / out["rollout_ms_per_design"] * 1e3
    out["speedup_batched"] = out["fea_s_per_episode"] / out["rollout_ms_per_design_batched"] * 1e3
    return out


@hydra.main(version_base="1.3", config_path="../conf", config_name="combine")
def main(cfg: DictConfig) -> None:
    report = combine([read_report(p) for p in cfg.reports])
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic.write_text(out_dir / "report.json", json.dumps(finite_or_null(report), indent=1, allow_nan=False))
    atomic.write_text(out_dir / "report.md", markdown(report))
    log.info("\n%s", markdown(report, with_designs=False))


if __name__ == "__main__":
    main()
