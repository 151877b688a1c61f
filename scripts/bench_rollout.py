"""Learned rollout wall time vs symmetry copies and batch size: `make bench-rollout CKPT=...` -> reports/bench_rollout/.

--checkpoint a.pt,b.pt times an ensemble (learn.ensemble: every member with the setting's copies).
Per backend (--backend: torchscript, the traced rollout; aot, every step an AOTInductor package, learn/aot.py) and
setting (rotations x mirror x lattice labellings, learn.rollout.answer_unroll): the compiled rollout of one design
from frame 0 to the rebuilt points of every frame, on one thread; the median over designs (the checkpoint's test split)
of the median of --repeats calls (learn.evaluate.median_seconds): the latency of one answer.
With --batch 8,32,...: also the rollout of that many designs at once (learn.rollout.rollout_many's disjoint union, the
test designs taken in turn), its median call time divided by the count: the cost per design of scoring many candidates.
Writes rollout.csv, rollout.md (machine, load, command) and rollout.png (ms vs copies and vs batch size, the 5 ms
target). Run it on an idle machine.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from data_schema import atomic  # noqa: E402

import torch  # noqa: E402

from learn import ensemble  # noqa: E402
from learn.dataset import load_features  # noqa: E402
from learn.aot import backend_checked  # noqa: E402
from learn.evaluate import median_seconds  # noqa: E402
from learn.rollout import compile_rollout, graph_inputs  # noqa: E402
from tradeoff import machine  # noqa: E402  (scripts/tradeoff.py)

TARGET_MS = 5.0  # ../shared/MISSION.md: <= 5 ms per design on one CPU core


def settings(text: str) -> list[tuple[int, bool, int]]:
    """'1:false,4:true,1:false:4' -> [(1, False, 1), (4, True, 1), (1, False, 4)]: rotations, mirror, lattice
    labellings (1 when left out)."""
    out = []
    for item in text.split(","):
        n, m, turns = (item.split(":") + ["1"])[:3] if item.count(":") in (1, 2) else ("", "", "")
        if m not in ("true", "false") or not n.isdigit() or int(n) < 1 or turns not in ("1", "2", "4"):
            raise SystemExit(f"--settings: {item!r} must be <rotations >= 1>:<true|false>[:<lattice turns 1|2|4>]")
        out.append((int(n), m == "true", int(turns)))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="runs/train/best.pt",
                   help="a checkpoint, or several joined by ',' (an ensemble), or a published models/<name>")
    p.add_argument("--data-dir", help="default: the checkpoint's data_dir")
    p.add_argument("--designs", type=int, default=8, help="test designs timed (the first by name)")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--settings", help="<rotations>:<mirror>[:<lattice turns>], comma-separated",
                   default="1:false,2:false,4:false,1:true,2:true,4:true,8:true,1:false:2,1:false:4,1:true:4")
    p.add_argument("--batch", default="", help="designs per call beside the one-design latency, comma-separated "
                   "(e.g. 8,32,128)")
    p.add_argument("--backend", default="torchscript",
                   help="compile_rollout backends timed, comma-separated: torchscript | aot | aot_tuned (aot: ~1 min "
                        "to compile per model, setting and batch size the first time, aot_tuned 3-5 min, then from "
                        "the cache)")
    p.add_argument("--aot-cache", help="where aot keeps its packages (default: learn.aot.default_cache)")
    p.add_argument("--out", default="reports/bench_rollout")
    a = p.parse_args()
    torch.set_num_threads(1)
    backends = [backend_checked(b) for b in a.backend.split(",")]
    sources = ensemble.checkpoint_paths(a.checkpoint.split(","))  # models/<name>: its members
    model, ckpt = ensemble.load(sources)
    members = len(ensemble.members_of(model))
    data_dir = Path(a.data_dir or ckpt["config"]["data_dir"])
    names = sorted(ckpt["split"]["test"])[: a.designs]
    if not names:
        raise SystemExit(f"{a.checkpoint} has no test split to time")
    features = load_features([data_dir / n for n in names])
    load_before = "/".join(f"{x:.2f}" for x in os.getloadavg())
    batches = [int(x) for x in a.batch.split(",") if x.strip()]
    if any(b < 2 for b in batches):
        raise SystemExit(f"--batch {a.batch}: every count must be >= 2 (1, one design, is always timed)")
    rows = []
    for backend, (n, mirror, turns) in ((b, s) for s in settings(a.settings) for b in backends):
        compiled = compile_rollout(model.answer_with(n, mirror, turns), features[0], backend, a.aot_cache)
        ms = [1e3 * median_seconds(lambda f=f: compiled(*graph_inputs(f)), a.repeats) for f in features]
        row = {"backend": backend, "members": members, "rotations": n, "mirror": mirror, "lattice_turns": turns,
               "copies": members * n * (2 if mirror else 1) * turns}
        rows.append({**row, "batch": 1, "ms_per_design": float(np.median(ms)), "ms_min": float(np.min(ms)),
                     "ms_max": float(np.max(ms))})
        for b in batches:
            inputs = graph_inputs([features[i % len(features)] for i in range(b)])
            with torch.inference_mode():
                compiled(*inputs)  # compiled here (a union of b designs has its own trace or package), not timed
            per_design = 1e3 * median_seconds(lambda: compiled(*inputs), max(3, a.repeats // 4)) / b
            rows.append({**row, "batch": b, "ms_per_design": per_design, "ms_min": per_design, "ms_max": per_design})
        for r in rows[-1 - len(batches):]:
            print(f"{backend}: rotations {n} mirror {mirror} lattice turns {turns} batch {r['batch']}: "
                  f"{r['ms_per_design']:.2f} ms/design", flush=True)
    load_after = "/".join(f"{x:.2f}" for x in os.getloadavg())

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic.write_csv(out / "rollout.csv", rows, list(rows[0]))
    lines = [f"# Learned rollout time vs symmetry copies ({a.checkpoint})", "",
             f"Machine: {machine()}; 1 torch thread; load average before/after {load_before} / {load_after}.",
             f"Command: `{' '.join([Path(sys.executable).name, *sys.argv])}`; {len(features)} test designs, "
             f"median of {a.repeats} calls each, then the median over designs (batch 1); batch b > 1: one call rolls "
             f"b designs out together, the median of {max(3, a.repeats // 4)} calls / b.", "",
             "| backend | members | rotations | mirror | lattice turns | copies | batch | ms per design (median) "
             "| min / max over designs |",
             "|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['backend']} | {r['members']} | {r['rotations']} | {r['mirror']} | {r['lattice_turns']} | "
              f"{r['copies']} | {r['batch']} | {r['ms_per_design']:.2f} | "
              + (f"{r['ms_min']:.2f} / {r['ms_max']:.2f} |" if r["batch"] == 1 else "|") for r in rows]
    atomic.write_text(out / "rollout.md", "\n".join(lines) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    single = [r for r in rows if r["batch"] == 1]
    fig, axes = plt.subplots(1, 2 if batches else 1, figsize=(11 if batches else 6, 4), squeeze=False)
    ax = axes[0, 0]
    groups = sorted({(r["backend"], r["mirror"], r["lattice_turns"]) for r in single})
    for (backend, mirror, turns), marker in zip(groups, "osD^v<>p" * 4):
        sel = [r for r in single if (r["backend"], r["mirror"], r["lattice_turns"]) == (backend, mirror, turns)]
        label = (f"{backend}: rotations" + (" + mirror" if mirror else "")
                 + (f" x {turns} labellings" if turns > 1 else ""))
        ax.plot([r["copies"] for r in sel], [r["ms_per_design"] for r in sel], marker + "-", label=label)
    ax.axhline(TARGET_MS, color="k", ls="--", lw=0.8, label=f"target {TARGET_MS:g} ms")
    ax.set(xlabel="copies averaged per answer", ylabel="rollout ms per design (1 thread)",
           title="one design: cost of symmetry averaging")
    ax.grid(alpha=0.3)
    ax.legend()
    if batches:
        ax = axes[0, 1]
        for key in dict.fromkeys((r["backend"], r["rotations"], r["mirror"], r["lattice_turns"]) for r in rows):
            sel = [r for r in rows if (r["backend"], r["rotations"], r["mirror"], r["lattice_turns"]) == key]
            ax.plot([r["batch"] for r in sel], [r["ms_per_design"] for r in sel], "o-",
                    label=f"{key[0]}: {sel[0]['copies']} cop{'y' if sel[0]['copies'] == 1 else 'ies'}")
        ax.axhline(TARGET_MS, color="k", ls="--", lw=0.8, label=f"target {TARGET_MS:g} ms")
        ax.set(xscale="log", yscale="log", xlabel="designs per call (one disjoint union)",
               ylabel="rollout ms per design (1 thread)", title="many designs at once")
        ax.grid(alpha=0.3, which="both")
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "rollout.png", dpi=110)
    plt.close(fig)
    print(out / "rollout.md")


if __name__ == "__main__":
    main()
