"""Batch dataset generation: sampled designs -> validated episode files, resumable and crash-safe.

    python -m fea_factory.generate n=200 out=data/episodes jobs=2 np=1 [mesh=coarse] [seed=0]
    python -m fea_factory.generate -m shard=0,1,2,3 n_shards=4 hydra/launcher=slurm   (a cluster)

Episode i (design seed from (seed, i)) is `out/episode_<i>.h5`. Each episode is solved in its own
`mpirun -n np` process, `jobs` of them at a time, so a crash or divergence takes down one episode only.
An episode file that validates is skipped on a re-run; the writer is atomic (temporary name, then rename),
so a kill at any moment leaves nothing that looks valid. Every attempt appends one JSON line to
`out/manifest.jsonl` (episode, seed, status ok | skipped | diverged | contact | error, reason, timings, bytes,
clearance_mm, attempt: the hash of what decides the outcome, `attempt_key`);
diverged and failed episodes are never written as data. A refusal (contact, diverged) is the physics' answer, not an
accident: a re-run does not solve that episode again while its design and solve settings are those refused
(`retry_refused=true` does); an `error` (a crash, a kill) is solved again.
Shard s of n_shards takes episodes i = s mod n_shards.
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from data_schema import atomic

from fea_factory.checks import integer_in
from fea_factory.design import Design
from fea_factory.material import make_material
from fea_factory.mesh import MeshPreset
from fea_factory.residual_stress import check_residual_stress
from fea_factory.scene import Scene
from fea_factory.solve import EXIT_CONTACT, EXIT_DIVERGED
from fea_factory.solver import SolverSettings
from fea_factory.tradeoff import apply_tolerance

ROOT = Path(__file__).resolve().parent.parent
SOLVE_GROUPS = ("blocks", "mesh", "material", "scene", "solver")
REFUSALS = ("contact", "diverged")  # the solve's own verdicts on a design: the same attempt gets the same answer
WRITTEN = ("ok", "skipped")  # a valid episode file on disk: solved, or found whole after a crash (kept, "skipped")


class GenerateConfigError(ValueError):
    """A generate.yaml value out of range, reported before any solve starts."""


def episode_path(out: Path, i: int) -> Path:
    return out / f"episode_{i:05d}.h5"


def check_config(cfg: DictConfig) -> None:
    """Build every physics object once, so that a bad value fails here and not after hours of solving."""
    for key, lo, meaning in (("n", 1, "episodes"), ("start", 0, "first episode index"), ("seed", 0, "design seed"),
                             ("jobs", 1, "episodes solved at once"), ("np", 1, "MPI ranks per episode"),
                             ("n_shards", 1, "processes sharing the episodes"), ("shard", 0, "this process's share")):
        integer_in(cfg[key], key, GenerateConfigError, lo, meaning=meaning)  # n=2.5 is refused, not run as 2
    if not isinstance(cfg.get("retry_refused"), bool):
        raise GenerateConfigError(f"retry_refused = {cfg.get('retry_refused')!r}: must be true or false")
    if not cfg.shard < cfg.n_shards:
        raise GenerateConfigError(f"shard = {cfg.shard}: must lie in [0, n_shards - 1 = {int(cfg.n_shards) - 1}]")
    # solver.tolerance: fail here if no measured setting meets it (each episode's solve picks again, with np ranks)
    apply_tolerance(cfg, ranks=int(cfg.np))
    MeshPreset.from_mapping(cfg.mesh)
    SolverSettings.from_mapping(cfg.solver)
    make_material(cfg.material)
    check_residual_stress(cfg.material.residual_stress)
    Scene.from_mapping(cfg.scene)


def solve_overrides(task_overrides: list[str]) -> list[str]:
    """The command-line overrides that concern the solve (conf groups and their fields), passed on."""
    keep = []
    for o in task_overrides:
        key = o.lstrip("+~").split("=", 1)[0]
        if key.split(".")[0].split("/")[0] in SOLVE_GROUPS:
            keep.append(o)
    return keep


def attempt_key(design: Design, cfg: DictConfig) -> str:
    """What decides an episode's outcome, hashed: the design (its JSON) and the resolved solve settings (the
    SOLVE_GROUPS of the conf, after solver.tolerance's pick, and the MPI ranks). Two attempts with one key solve the
    same problem; a change of design or of any solve setting makes a new key."""
    solve = {g: OmegaConf.to_container(cfg[g], resolve=True) for g in SOLVE_GROUPS}
    text = json.dumps({"design": design.to_dict(), "solve": solve, "np": int(cfg.np)}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class Manifest:
    """Append-only JSON lines, one per episode attempt; flushed and fsynced line by line."""

    def __init__(self, path: Path):
        self.path, self.lock = path, threading.Lock()

    def records(self) -> list[dict]:
        """Every record, in order (a torn last line from a kill is ignored)."""
        found = []
        if self.path.exists():
            for line in self.path.read_text().splitlines():
                try:
                    found.append(json.loads(line))
                except json.JSONDecodeError:
                    continue
        return found

    def episodes_with_status(self, *statuses: str) -> set[int]:
        """Episodes that have a record with one of `statuses`."""
        return {int(rec["episode"]) for rec in self.records() if rec.get("status") in statuses}

    def refused_attempts(self) -> set[tuple[int, str]]:
        """(episode, attempt key) of every refusal on record (records before the key was recorded have none)."""
        return {(int(rec["episode"]), rec["attempt"]) for rec in self.records()
                if rec.get("status") in REFUSALS and rec.get("attempt")}

    def append(self, record: dict) -> None:
        line = json.dumps(record, sort_keys=True) + "\n"
        with self.lock, open(self.path, "a") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())


def mpirun_env() -> dict:
    """The environment for a fresh mpirun: without the variables of an MPI job we may be running inside
    (a parent that called MPI_Init exports OMPI_*/PMIX_*, and a nested mpirun then exits silently)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_", "OPAL_", "ORTE_"))}
    env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMP_NUM_THREADS="1")
    return env


def run_episode(i: int, design: Design, out: Path, cfg: DictConfig, overrides: list[str]) -> dict:
    """Solve one design in an MPI subprocess; return its manifest record."""
    attempt = attempt_key(design, cfg)
    path = episode_path(out, i)
    design_dir = out / "designs"
    design_dir.mkdir(exist_ok=True)
    design_file = design_dir / f"episode_{i:05d}.json"
    design.save(design_file)
    env = mpirun_env()
    # --bind-to none: every mpirun binds its rank 0 to core 0 by default, so `jobs` concurrent episodes
    # would share one core (measured: two jobs at 47 % CPU each)
    cmd = ["mpirun", "--bind-to", "none", "-n", str(cfg.np), sys.executable, "-m", "fea_factory.solve",
           f"design={design_file}", f"out={path}", f"seed={design.meta.get('seed', cfg.seed)}", *overrides]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, stdin=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    record = {"episode": i, "seed": int(cfg.seed), "design": str(design_file), "wall_s": round(wall, 3),
              "attempt": attempt, "family": design.meta.get("family"), "actuators": design.meta.get("actuators")}
    last = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    try:
        result = json.loads(last)
    except json.JSONDecodeError:
        result = {}
    if proc.returncode == 0 and result.get("status") == "ok":
        return {**record, "status": "ok", "file": str(path), "bytes": path.stat().st_size,
                "increments": result.get("increments"), "newton": result.get("newton"),
                "cutbacks": result.get("cutbacks"), "newton_failed": result.get("newton_failed"),
                "solve_wall_s": result.get("wall_total_s"),
                "clearance_mm": result.get("clearance_mm")}
    if proc.returncode == EXIT_CONTACT:
        return {**record, "status": "contact", "reason": result.get("reason"),
                "clearance_mm": result.get("clearance_mm")}
    if proc.returncode == EXIT_DIVERGED:
        return {**record, "status": "diverged", "reason": result.get("reason"), "t": result.get("t"),
                **{k: result[k] for k in ("last_t", "last_clearance_mm", "last_clearance_blocks") if k in result}}
    tail = (proc.stderr or proc.stdout)[-1500:]
    return {**record, "status": "error", "returncode": proc.returncode, "reason": tail}


class GeneratorInUse(atomic.InUse):
    """Another live generator works on the same shard of the same out directory."""


def generate(cfg: DictConfig, task_overrides: list[str] | None = None) -> dict:
    """Generate the episodes of this shard; returns the summary."""
    check_config(cfg)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    # one generator per shard of out: a second would solve the same episodes and remove the first's temporaries
    with atomic.held(out / f".generate.shard{cfg.shard}of{cfg.n_shards}.lock",
                     f"out={out} (shard {cfg.shard} of {cfg.n_shards})", GeneratorInUse):
        return _generate(cfg, out, task_overrides)


def _generate(cfg: DictConfig, out: Path, task_overrides: list[str] | None) -> dict:
    from tqdm import tqdm

    from data_schema.validate import validate_episode
    from fea_factory.sample import sample_designs

    manifest = Manifest(out / "manifest.jsonl")
    mine = [i for i in range(int(cfg.start), int(cfg.start) + int(cfg.n)) if i % int(cfg.n_shards) == int(cfg.shard)]
    for i in mine:  # a killed writer leaves <name>.h5.<hex>.tmp behind: ours to remove
        for stale in out.glob(f"episode_{i:05d}.h5.*tmp"):
            stale.unlink()
    todo, skipped = [], 0
    recorded = manifest.episodes_with_status(*WRITTEN)
    for i in mine:
        path = episode_path(out, i)
        if path.exists() and not validate_episode(path):
            skipped += 1
            if i not in recorded:  # written, then the generator died before its manifest line
                manifest.append({"episode": i, "seed": int(cfg.seed), "status": "skipped", "file": str(path),
                                 "bytes": path.stat().st_size,
                                 "reason": "valid episode file without a manifest record (generator killed "
                                           "after writing it); kept"})
            continue
        if path.exists():
            path.unlink()  # present but invalid: solve again
        todo.append(i)
    overrides = solve_overrides(task_overrides or [])
    designs = {i: sample_designs(cfg.grid, cfg.blocks, n=1, seed=int(cfg.seed), start=i)[0] for i in todo}
    refused_before = []
    if not cfg.retry_refused:
        refused = manifest.refused_attempts()
        refused_before = [i for i in todo if (i, attempt_key(designs[i], cfg)) in refused]
        standing = set(refused_before)
        todo = [i for i in todo if i not in standing]
        if refused_before:
            print(f"generate: {len(refused_before)} episode(s) refused before with this design and these solve "
                  f"settings, not solved again (retry_refused=true solves them): {refused_before[:10]}"
                  f"{' ...' if len(refused_before) > 10 else ''}", file=sys.stderr)
    counts = {"ok": 0, "diverged": 0, "contact": 0, "error": 0}
    n_bytes = 0
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=int(cfg.jobs)) as pool, \
            tqdm(total=len(todo), desc=f"episodes (shard {cfg.shard})", unit="ep", disable=not cfg.progress) as bar:
        futures = [pool.submit(run_episode, i, designs[i], out, cfg, overrides) for i in todo]
        for fut in as_completed(futures):  # record each episode as soon as it ends, not in submission order
            rec = fut.result()
            manifest.append(rec)
            counts[rec["status"]] += 1
            n_bytes += rec.get("bytes", 0)
            bar.set_postfix(ok=counts["ok"], failed=counts["diverged"] + counts["contact"] + counts["error"])
            bar.update()
    wall = time.perf_counter() - t0
    summary = {"done": counts["ok"], "skipped": skipped, "refused_before": len(refused_before),
               "diverged": counts["diverged"], "contact": counts["contact"],
               "error": counts["error"],
               "bytes": n_bytes, "bytes_per_episode": n_bytes // max(counts["ok"], 1), "wall_s": round(wall, 2),
               "episodes_per_hour": round(3600 * counts["ok"] / wall, 1) if counts["ok"] else 0.0,
               "jobs": int(cfg.jobs), "np": int(cfg.np), "out": str(out)}
    print(json.dumps(summary))
    return summary


def main() -> None:
    import hydra
    from hydra.core.hydra_config import HydraConfig

    @hydra.main(version_base="1.3", config_path="../conf", config_name="generate")
    def _main(cfg: DictConfig) -> None:
        try:
            summary = generate(cfg, list(HydraConfig.get().overrides.task))
        except (ValueError, KeyError) as err:
            print(f"generate: invalid configuration: {err}", file=sys.stderr)
            sys.exit(2)
        except GeneratorInUse as err:
            print(f"generate: {err}", file=sys.stderr)
            sys.exit(3)
        if summary["error"]:
            sys.exit(1)

    _main()


if __name__ == "__main__":
    main()
