"""Evaluate a trained simulator against FEA on a held-out split: `.venv/bin/python -m learn.evaluate` (conf/evaluate.yaml).

Writes report.json (machine-readable), report.md (table) and plots into out_dir.
"""
from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from data_schema import atomic
from learn import ensemble
from learn.checks import integer_in, number_in
from learn.dataset import design_paths, episode_paths, load_features
from learn.features import EpisodeFeatures, rebuild_all_points
from learn.model import Simulator
from learn.rigid import shape_error
from learn.roll import ONE_KIND, ROLLED, roll
from learn.aot import AOT_BACKENDS, backend_checked
from learn.rollout import (answer_unroll, compile_rollout, graph_inputs, input_floor, plain_inputs, reference,
                           rollout)
from learn.validity import check, thresholds

log = logging.getLogger(__name__)


def distribution(x) -> dict:
    x = np.asarray(x, dtype=np.float64)
    if len(x) == 0:
        return {"median": None, "p95": None, "worst": None, "n": 0}
    return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95)), "worst": float(x.max()),
            "n": int(len(x))}


def with_groups(values: list[float], **groups: list[str]) -> dict:
    """The distribution of `values`, and per_<name> its distribution within each label of every grouping given
    (per_family: the sampler's random | regular; per_actuators: all up | all down | ... | mixed)."""
    out = distribution(values)
    for name, labels in groups.items():
        out[f"per_{name}"] = {lab: distribution([v for v, g in zip(values, labels) if g == lab])
                              for lab in sorted(set(labels))}
    return out


def rank_correlation(x, y) -> float:
    """Spearman's rho (ranks, ties broken by order): does x order the designs as y does?"""
    rx, ry = (np.argsort(np.argsort(np.asarray(v, dtype=np.float64))) for v in (x, y))
    return float(np.corrcoef(rx, ry)[0, 1]) if len(rx) > 1 else float("nan")


# how a report's designs are grouped (with_groups: per_<name> in the report, a row per label in markdown)
GROUPINGS = {"family": lambda d: d["family"],  # the sampler's random | regular
             "actuators": lambda d: d.get("actuators", "unknown")}  # all up | all down | ...; older reports: unknown


def by_frame(designs: list[dict]) -> dict | None:
    """Per frame k, over the designs: the median and p95 of the max error / design size, and the median FEA step
    (the largest node motion from frame k-1 to k / design size), so the error's growth reads against the motion it
    follows. None when the designs' frame counts differ or a report predates the FEA step."""
    errors = [d["max_rel_error_per_frame"] for d in designs]
    steps = [d.get("fea_step_rel_per_frame") for d in designs]
    if not designs or any(s is None for s in steps) or len({len(e) for e in errors + steps}) != 1:
        return None
    errors, steps = np.asarray(errors, dtype=np.float64), np.asarray(steps, dtype=np.float64)
    return {"max_rel_error_median": np.median(errors, 0).tolist(),
            "max_rel_error_p95": np.percentile(errors, 95, axis=0).tolist(),
            "fea_step_rel_median": np.median(steps, 0).tolist()}


# what the validity check reads, per design (learn.validity.Verdict fields): how well each ranks designs by error
VALIDITY_INDICATORS = ("max_dislocation_rel", "out_of_range_fraction", "unrolled_one_kind", "max_spread_rel")


def validity_indicators(designs: list[dict]) -> dict[str, np.ndarray]:
    """The indicators of VALIDITY_INDICATORS that every design's verdict holds: their values [N] (nan as inf)."""
    out = {}
    for key in VALIDITY_INDICATORS:
        values = [d.get("validity", {}).get(key) for d in designs]
        if designs and all(v is not None for v in values):
            out[key] = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=np.inf)
    return out


def flag_outcome(errors: np.ndarray, flagged: np.ndarray, error_rel: float) -> dict:
    """What flagging `flagged` [N] does against the bad designs (max error > error_rel of the design size): of the
    bad ones how many it flags (caught), of the others how many needlessly (false_flags), Youden's J (the share of
    bad flagged - the share of good flagged) and the error distributions of the passed and the flagged."""
    bad = errors > error_rel
    n_bad, n_good = int(bad.sum()), int((~bad).sum())
    caught, false = int((bad & flagged).sum()), int((~bad & flagged).sum())
    return {"n": len(errors), "n_bad": n_bad, "caught": caught, "false_flags": false,
            "caught_share": caught / n_bad if n_bad else None, "false_share": false / n_good if n_good else None,
            "youden_j": (caught / n_bad if n_bad else 0.0) - (false / n_good if n_good else 0.0),
            "passed": distribution(errors[~flagged]), "flagged": distribution(errors[flagged])}


def validity_measured(designs: list[dict], flag_error_rel: float) -> dict:
    """How well the validity check separates bad answers (max error > flag_error_rel of the design size) from the
    rest (flag_outcome of its verdicts), and each indicator's Spearman rank correlation with the error (1: it
    orders the designs exactly as the error does)."""
    errors = np.array([d["max_rel_error"] for d in designs], dtype=np.float64)
    flagged = np.array([not d["valid"] for d in designs], dtype=bool)
    return {"flag_error_rel": float(flag_error_rel), "n_flagged": int(flagged.sum()),
            **flag_outcome(errors, flagged, flag_error_rel),
            "spearman": {k: rank_correlation(v, errors) for k, v in validity_indicators(designs).items()}}


def design_statistics(designs: list[dict], flag_error_rel: float | None = None) -> dict:
    """The error distributions of a report over its per-design entries (overall and per family for the errors);
    for an ensemble also its members' spread and how well the spread ranks the designs by error; with
    flag_error_rel, how well the validity check finds the designs worse than that (validity_measured)."""
    groups = {name: [label(d) for d in designs] for name, label in GROUPINGS.items()}
    out = {
        "n_designs": len(designs),
        "n_compiled_departures": int(sum("compiled_gap_mm" in d for d in designs)),  # learn.evaluate.mark_departures
        "max_rel_error": with_groups([d["max_rel_error"] for d in designs], **groups),
        "mean_rel_error": with_groups([d["mean_rel_error"] for d in designs], **groups),
        **({"shape_rel_error": with_groups([d["shape_rel_error"] for d in designs], **groups)}
           if designs and all("shape_rel_error" in d for d in designs) else {}),  # reports since session 65
        "representation_floor": distribution([d["representation_floor"] for d in designs]),
        "input_floor": distribution([d["input_floor"] for d in designs]),
    }
    spread = [d.get("spread_rel") for d in designs]
    if designs and all(v is not None for v in spread):
        out["spread_rel"] = distribution(spread)
        out["spread_error_spearman"] = rank_correlation(spread, [d["max_rel_error"] for d in designs])
    frames = by_frame(designs)
    if frames is not None:
        out["by_frame"] = frames
    if flag_error_rel is not None:
        out["validity_measured"] = validity_measured(designs, flag_error_rel)
    agreement = roll_agreement(designs)
    if agreement is not None:
        out["roll_agreement"] = agreement
    return out


def roll_agreement(designs: list[dict]) -> dict | None:
    """Of the all-one-kind designs (those with a "roll": s_i - s_j of the answer and of the FEA, learn.roll), how
    many the FEA rolls (|s_i - s_j| > ROLLED) and how many of those the answer rolls the same way, leaves unrolled or
    rolls the other way; None when there are none."""
    rolls = [d["roll"] for d in designs if "roll" in d]
    if not rolls:
        return None
    fea = np.array([x["fea"] for x in rolls])
    answer = np.array([x["answer"] for x in rolls])
    rolled = np.abs(fea) > ROLLED
    answered = np.abs(answer) > ROLLED
    return {"n_one_kind": len(rolls), "fea_rolled": int(rolled.sum()),
            "same_way": int((rolled & answered & (np.sign(answer) == np.sign(fea))).sum()),
            "unrolled": int((rolled & ~answered).sum()),
            "other_way": int((rolled & answered & (np.sign(answer) != np.sign(fea))).sum()),
            "roll_gap": distribution(np.abs(answer - fea))}


def fea_steps(f: EpisodeFeatures) -> np.ndarray:
    """[F] the largest motion of a rebuilt point from the FEA's frame k-1 to frame k / design size (0 at frame 0)."""
    step = np.linalg.norm(np.diff(f.fea_points, axis=0), axis=-1).max(axis=1) / f.design_size
    return np.concatenate([[0.0], step])


def median_seconds(fn, repeats: int) -> float:
    """Median wall time of fn() over `repeats` calls after one warm-up call."""
    times = []
    with torch.inference_mode():
        for _ in range(repeats + 1):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
    return float(np.median(times[1:]))


def eager_rollout(model: Simulator, f: EpisodeFeatures):
    """One design's rollout from its initial graph to the rebuilt points of every frame, eager PyTorch."""
    inputs = plain_inputs(f)
    return lambda: rebuild_all_points(*answer_unroll(model, *inputs))


def busy(load: float, threads: int, cpus: int | None = None) -> bool:
    """Whether a timing was taken on a busy machine: the 1-minute load average (runnable threads, this process's
    `threads` included) more than half a thread above what the CPUs (or those threads) can run at once, so other
    work took CPU time from the rollouts."""
    return load > max(cpus or os.cpu_count() or 1, threads) + 0.5


# the compiled rollout must give the eager numbers to float32 rounding grown over the steps: 1e-4 of the design size
# (0.02 mm at 200 mm, ~100x below the best answers' errors; a wide model on a bifurcating design reached 2e-5, session
# 34), far below what a compile fault does
COMPILED_GAP_REL = 1e-4


def departures(compiled, model: Simulator, features: list[EpisodeFeatures]) -> list[dict]:
    """The designs whose compiled rollout departs from the eager one by more than COMPILED_GAP_REL of their size: index,
    the largest point gap (mm) and the compiled answer's own max error / design size."""
    out = []
    with torch.inference_mode():
        for i, f in enumerate(features):
            got = compiled(*graph_inputs(f))[2].numpy()
            gap = float(np.abs(got - eager_rollout(model, f)().numpy()).max())
            if not gap <= COMPILED_GAP_REL * f.design_size:  # nan departs too
                error = np.linalg.norm(got - f.fea_points, axis=-1).max() / f.design_size
                out.append({"index": i, "gap_mm": gap, "compiled_max_rel_error": float(error)})
    return out


def timings(model: Simulator, features: list[EpisodeFeatures], repeats: int, backend: str = "torchscript",
            cache: str | None = None) -> dict:
    """Seconds per design: one design at a time (compiled by `backend`, learn.rollout.compile_rollout, and eager) and
    all designs as one graph (compiled, over their count); the machine's 1-minute load average after them (`busy`
    says whether they are upper bounds); the designs where the compiled rollout departs from eager (`departures`)."""
    start = time.perf_counter()
    compiled = compile_rollout(model, features[0], backend, cache)
    compile_s = time.perf_counter() - start
    departed = departures(compiled, model, features)
    with torch.inference_mode():
        together = graph_inputs(features)  # every design as one disjoint union (learn.rollout.rollout_many)
        compiled(*together)  # traced here, outside the timing
    return {
        "compiled": float(np.median([median_seconds(lambda: compiled(*graph_inputs(f)), repeats) for f in features])),
        "eager": float(np.median([median_seconds(eager_rollout(model, f), repeats) for f in features])),
        "batched": median_seconds(lambda: compiled(*together), repeats) / len(features),
        "compile": compile_s,
        "load": os.getloadavg()[0],
        "departures": departed,
    }


def mark_departures(designs: list[dict], departed: list[dict], allowed: float, backend: str) -> None:
    """Flag each design whose compiled rollout departs from eager as invalid (a bifurcation, where the order of float
    sums picks the answer: the deployed answer is not the one measured), its gap and the compiled answer's error
    beside the eager errors; more than `allowed` (a fraction of the designs) departing is a compile fault, raised."""
    if len(departed) > allowed * len(designs):
        names = ", ".join(f"{designs[d['index']]['name']} ({d['gap_mm']:.3g} mm)" for d in departed[:5])
        hint = (f"; rollout_backend={backend} sums in another order than eager, so at a bifurcation rounding can "
                "grow: time it with rollout_backend=torchscript (make reference-evaluate BACKEND=torchscript) and compare"
                if backend in AOT_BACKENDS else "")
        raise RuntimeError(f"compiled rollout differs from eager by more than {COMPILED_GAP_REL:g} of the design size "
                           f"on {len(departed)} of {len(designs)} designs: {names}{', ...' if len(departed) > 5 else ''}"
                           f"; compiled_departures={allowed:g} allows {int(allowed * len(designs))}{hint}")
    for d in departed:
        design = designs[d["index"]]
        design["compiled_gap_mm"] = d["gap_mm"]
        design["compiled_max_rel_error"] = d["compiled_max_rel_error"]
        design["valid"] = design["validity"]["valid"] = False
        design["validity"]["reasons"] = [*design["validity"]["reasons"],
                                         f"the compiled rollout departs from eager by {d['gap_mm']:.3g} mm (more than "
                                         f"{COMPILED_GAP_REL:g} of the size): a bifurcation, float rounding picks the "
                                         f"answer; compiled answer's max error {100 * d['compiled_max_rel_error']:.3g} %"]


def share_of_designs_checked(value, name: str) -> float:
    """A share of the evaluated designs in [0, 1] (1 included, unlike learn.gn.fraction_checked's rates)."""
    return number_in(value, name, 0, 1, "a fraction of the designs, e.g. 0.05")


def flag_error_rel_checked(value, name: str = "flag_error_rel") -> float:
    """An error level a flag is judged against: a fraction of the design size in (0, 1)."""
    return number_in(value, name, 0, 1, "a fraction of the design size, e.g. 0.10", low_open=True, high_open=True)


def split_paths(split: str, stored: dict[str, list[str]], data_dir: Path, source: str,
                config: dict | None = None) -> list[Path]:
    """Episode paths of `split`: 'all' (every *.h5 in data_dir, e.g. designs generated apart from training),
    'unseen' (every *.h5 in data_dir the checkpoint did not train on: its val and test designs and any generated
    since), one split stored in the checkpoint, or several joined by '+' (val+test: the pinned held-out designs); a
    stored split's designs read from the checkpoint config's train_extra_dirs are found there (design_paths)."""
    if split == "all":
        return episode_paths(data_dir)
    if split == "unseen":
        trained_on = set(stored.get("train", []))
        return [p for p in episode_paths(data_dir) if p.name not in trained_on]
    names = str(split).split("+")
    unknown = [n for n in names if n not in stored]
    if unknown:
        raise ValueError(f"split={split!r}: allowed are {sorted(stored)} (stored in {source}), several of them "
                         "joined by '+', 'all' (every *.h5 in data_dir) or 'unseen' (those not trained on)")
    return design_paths([e for n in dict.fromkeys(names) for e in stored[n]], data_dir, config)


BUSY_LOAD_PER_CPU = 1.25  # FEA on a busy machine: as `busy` for rollout timings, half a thread over 2 CPUs


def fea_load_mean(features) -> float:
    """The mean machine load per CPU recorded around the test episodes' FEA solves (provenance), as the speed-up uses
    their mean wall time (a mean, not the highest: the 1-minute load average lags, so the first solves after other
    work read high), NaN if none recorded."""
    loads = [f.fea_load_per_cpu for f in features if np.isfinite(f.fea_load_per_cpu)]
    return float(np.mean(loads)) if loads else float("nan")


def busy_note(load: float | None) -> str:
    """A warning for the report when FEA wall times were taken on a busy machine (the speed-up is overstated)."""
    if load is None or not load > BUSY_LOAD_PER_CPU:
        return ""
    return (f" (measured on a busy machine: load {load:.2f} per CPU on average, over {BUSY_LOAD_PER_CPU}; the FEA times "
            "and so the speed-up are overstated: regenerate the episodes on a quiet machine)")


def evaluate(cfg: DictConfig) -> dict:
    torch.set_num_threads(integer_in(cfg.threads, "threads", 1, 1024, "torch threads while rolling out and timing"))
    repeats = integer_in(cfg.timing_repeats, "timing_repeats", 1, 1000, "timed rollouts per design, median taken")
    backend = backend_checked(cfg.get("rollout_backend", "torchscript"))  # refused before any rollout
    allowed = share_of_designs_checked(cfg.get("compiled_departures", 0.05), "compiled_departures")
    sources = ensemble.checkpoint_paths(cfg.checkpoint)
    model, ckpt = ensemble.load(sources)
    model.answer_with(cfg.rollout_rotations, cfg.rollout_mirror, cfg.rollout_lattice_turns)
    limits = thresholds(OmegaConf.to_container(cfg.validity), model)  # those of the model's frame
    data_dir = Path(cfg.data_dir or ckpt["config"]["data_dir"])
    paths = split_paths(cfg.split, ckpt["split"], data_dir, sources[0], ckpt["config"])
    if not paths:
        raise ValueError(f"split {cfg.split!r} of {sources[0]} is empty")
    features = load_features(paths)
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    weld = bool(cfg.get("weld", False))
    designs, rollouts = [], []
    for f in features:
        raw = rollout(model, f, steps=f.n_frames - 1, t=f.t)
        verdict = check(model, raw, **limits, envelope=ckpt.get("envelope"))
        r = raw.welded() if weld else raw  # the answer measured; the check reads the blocks as predicted
        err = np.linalg.norm(r.local_points - f.fea_points, axis=-1)  # [F, P]
        floor = np.linalg.norm(reference(f).local_points - f.fea_points, axis=-1)
        shape = shape_error(r.local_points.astype(np.float64), f.fea_points.astype(np.float64))  # [F]
        seen = input_floor(model, f)
        designs.append({
            "name": f.name, "family": f.family, "actuators": f.actuators, "design_size_mm": f.design_size,
            "max_rel_error": float(err.max() / f.design_size), "mean_rel_error": float(err.mean() / f.design_size),
            "max_error_mm": float(err.max()),
            "max_rel_error_per_frame": (err.max(axis=1) / f.design_size).tolist(),
            "mean_rel_error_per_frame": (err.mean(axis=1) / f.design_size).tolist(),
            "fea_step_rel_per_frame": fea_steps(f).tolist(),
            "shape_rel_error": float(shape.max() / f.design_size),
            "shape_rel_error_per_frame": (shape / f.design_size).tolist(),
            "representation_floor": float(floor.max() / f.design_size),
            "input_floor": float(seen.max() / f.design_size),
            "fea_s": f.fea_seconds, "valid": verdict.valid, "validity": verdict.as_dict(),
            "spread_rel": verdict.max_spread_rel,
            **({"roll": {"answer": roll(f, r.local_points), "fea": roll(f, f.fea_points)}}
               if f.actuators in ONE_KIND else {})})
        rollouts.append(r)

    times = timings(model, features, repeats, backend, cfg.get("aot_cache"))
    mark_departures(designs, times["departures"], allowed, backend)
    rollout_s, batched_s = times["compiled"], times["batched"]
    fea_s = float(np.nanmean([f.fea_seconds for f in features])) if any(
        np.isfinite(f.fea_seconds) for f in features) else float("nan")
    report = {
        **design_statistics(designs, flag_error_rel_checked(cfg.flag_error_rel)),
        "rollout_ms_per_design": 1e3 * rollout_s,
        "rollout_ms_per_design_eager": 1e3 * times["eager"],
        "rollout_ms_per_design_batched": 1e3 * batched_s,
        "compile_s": times["compile"],
        "rollout_backend": backend,
        "fea_s_per_episode": fea_s,
        "fea_load_per_cpu_mean": fea_load_mean(features),
        "speedup": fea_s / rollout_s,
        "speedup_batched": fea_s / batched_s,
        "n_invalid": int(sum(not d["valid"] for d in designs)),
        "welded": weld,
        "threads": int(cfg.threads),
        "load_average": times["load"], "cpus": os.cpu_count(),
        "timing_busy": busy(times["load"], int(cfg.threads)),
        "steps": int(features[0].n_frames - 1),
        "checkpoint": sources[0] if len(sources) == 1 else sources, "split": cfg.split, "data_dir": str(data_dir),
        "model": {k: v for k, v in model.args.items() if k != "pca"}, "n_parameters": model.n_parameters,
        "timing": "rollout_ms_per_design: median over designs of the median wall time of one design's rollout "
                  "(initial graph -> rebuilt points of every frame), compiled once per model (compile_s) by "
                  "rollout_backend (torchscript: a traced rollout; aot: each step an AOTInductor package, "
                  "learn/aot.py), "
                  "on `threads` CPU threads; _eager: plain PyTorch; _batched: all designs rolled out together as one "
                  "graph (compiled, learn.rollout.rollout_many's union), the call's time over their count. "
                  "FEA: mean of the episodes' provenance wall_s.total",
        "validity_thresholds": limits,
        "designs": designs,
    }
    atomic.write_text(out_dir / "report.json", json.dumps(finite_or_null(report), indent=1, allow_nan=False))
    atomic.write_text(out_dir / "report.md", markdown(report))
    if cfg.plots:
        from learn.plots import plot_report
        plot_report(report, rollouts, out_dir)
    log.info("\n%s", markdown(report, with_designs=False))
    return report


def finite_or_null(x):
    """NaN/inf -> None throughout, so the report is strict JSON."""
    if isinstance(x, dict):
        return {k: finite_or_null(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite_or_null(v) for v in x]
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.2f}%"


def markdown(report: dict, with_designs: bool = True) -> str:
    m = report["max_rel_error"]
    lines = [
        f"# Learned rollout vs FEA ({report['n_designs']} designs, split {report['split']})", "",
        "| | median | p95 | worst | n |", "|---|---|---|---|---|",
        f"| max error / design size | {_pct(m['median'])} | {_pct(m['p95'])} | {_pct(m['worst'])} | {m['n']} |",
        *(f"| ... {group} | {_pct(d['median'])} | {_pct(d['p95'])} | {_pct(d['worst'])} | {d['n']} |"
          for name in GROUPINGS for group, d in m.get(f"per_{name}", {}).items()),
        f"| mean error / design size | {_pct(report['mean_rel_error']['median'])} | "
        f"{_pct(report['mean_rel_error']['p95'])} | {_pct(report['mean_rel_error']['worst'])} | |",
        *(f"| {label} | {_pct(report[key]['median'])} | {_pct(report[key]['p95'])} | {_pct(report[key]['worst'])} | |"
          for key, label in (("shape_rel_error", "shape error / design size (the answer moved rigidly onto the FEA's)"),
                             ("representation_floor", "representation floor"), ("input_floor", "input floor (PCA)"))
          if key in report),
        "",
        f"rollout {report['rollout_ms_per_design']:.2f} ms/design ({report.get('rollout_backend', 'torchscript')}, "
        f"{report['threads']} thread; eager "
        f"{report['rollout_ms_per_design_eager']:.2f} ms), batched "
        f"{report['rollout_ms_per_design_batched']:.3f} ms/design; FEA {report['fea_s_per_episode']:.3g} s/episode"
        f"{busy_note(report.get('fea_load_per_cpu_mean', float('nan')))}; "
        f"speed-up {report['speedup']:.3g}x (batched {report['speedup_batched']:.3g}x); "
        f"{report['n_invalid']} rollouts flagged invalid"
        + (f" ({report['n_compiled_departures']} where the compiled rollout departs from eager: bifurcations, their "
           "errors those of the eager answer)" if report.get("n_compiled_departures") else ""),
    ]
    if "validity_measured" in report:
        v = report["validity_measured"]
        rho = ", ".join(f"{k} {x:.2f}" for k, x in v["spearman"].items())
        lines += ["", f"Validity check against max error > {_pct(v['flag_error_rel'])}: {v['caught']} of {v['n_bad']} "
                  f"such designs flagged, {v['false_flags']} of {report['n_designs'] - v['n_bad']} others flagged "
                  f"needlessly; passed designs {_pct(v['passed']['median'])} median, {_pct(v['passed']['p95'])} p95; "
                  f"flagged {_pct(v['flagged']['median'])} median. Spearman with the error: {rho}"]
    if "roll_agreement" in report:
        a = report["roll_agreement"]
        lines += ["", f"All-one-kind designs ({a['n_one_kind']}): the FEA rolls {a['fea_rolled']} (|s_i - s_j| > "
                  f"{ROLLED}); the answer rolls {a['same_way']} of them the same way, {a['unrolled']} not, "
                  f"{a['other_way']} the other way; |answer - FEA| of s_i - s_j {a['roll_gap']['median']:.3f} median, "
                  f"{a['roll_gap']['worst']:.3f} worst"]
    if report.get("timing_busy"):
        lines += ["", f"Timed on a busy machine (1-minute load {report['load_average']:.1f} on {report['cpus']} "
                  "CPUs): the times are upper bounds and the speed-ups lower bounds; time on an idle machine with "
                  "scripts/bench_rollout.py (make bench-rollout)."]
    if "spread_rel" in report:
        sp = report["spread_rel"]
        lines += ["", f"ensemble of {report['model'].get('ensemble_members')}: members' spread / design size "
                  f"{_pct(sp['median'])} median, {_pct(sp['p95'])} p95, {_pct(sp['worst'])} worst; Spearman with the "
                  f"max error {report['spread_error_spearman']:.2f}"]
    if "by_frame" in report:
        fr = report["by_frame"]
        lines += ["", "By frame (the max over frames is mostly the last one's):", "",
                  "| frame | " + " | ".join(str(k) for k in range(1, len(fr["fea_step_rel_median"]))) + " |",
                  "|---" * len(fr["fea_step_rel_median"]) + "|",
                  *("| " + label + " | " + " | ".join(_pct(v) for v in fr[key][1:]) + " |"
                    for key, label in (("max_rel_error_median", "max error, median"),
                                       ("max_rel_error_p95", "max error, p95"),
                                       ("fea_step_rel_median", "FEA step, median")))]
    if with_designs:
        lines += ["", "| design | family | actuators | size mm | max err | shape err | mean err | floor | valid |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for d in sorted(report["designs"], key=lambda d: d["max_rel_error"]):
            lines.append(f"| {d['name']} | {d['family']} | {d.get('actuators', '-')} | {d['design_size_mm']:.1f} | "
                         f"{_pct(d['max_rel_error'])} | {_pct(d.get('shape_rel_error'))} | "
                         f"{_pct(d['mean_rel_error'])} | {_pct(d['representation_floor'])} | "
                         f"{'yes' if d['valid'] else 'NO: ' + '; '.join(d['validity']['reasons'])} |")
    return "\n".join(lines) + "\n"


@hydra.main(version_base="1.3", config_path="../conf", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    evaluate(cfg)


if __name__ == "__main__":
    main()
