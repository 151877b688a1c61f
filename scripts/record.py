"""The record model rebuilt from nothing, stage by stage (conf/record.yaml), so a fresh machine gets back to it by
re-running the same commands session after session:

    make record-data JOBS=2          # every episode conf/record.yaml lists that no feature pack holds (resumable)
    make record-pack                 # the features of what it solved -> packs/<data dir>/part_*.h5: commit them
    make record BUDGET_MIN=150       # every seed's stages side by side, one core each (SEED=0: one seed alone)
    make record-evaluate             # the pair's last stages on the 102 held-out designs, then models/<publish_as>

`train` runs the stages of one seed in order. A finished stage is skipped; a started one resumes from its last.pt;
each gets a time limit that ends it before the budget of this invocation runs out (learn.train's time_limit_min counts
a run's training minutes over all its invocations, so the limit is the minutes done plus what the budget leaves),
and a stage that pauses stops the chain: the next stage never starts from an unfinished one. A stage starts only when
the budget leaves one epoch of it (learn.train always trains one epoch before it looks at its limit; an epoch as long
as the stage's own last one, or the last one of the latest stage with the same args) and its data are complete
(generated or refused by the solver), so every seed trains on the same designs: by default every episode of `data`;
a stage's `needs` ({out: n}) asks for the first n episodes of those entries only (the reference stage reads the first
400 of data/ds_default), so it trains on one core while the other generates the rest
(`make record-data JOBS=1`). With `--wait` (make record WAIT=1) a stage whose data are not complete waits for
them within the budget instead of exiting 4, so one command can follow a generator started beside it. A stage with
`keep: <file>` is published when it finishes (learn.publish, without the optimiser: ~7 MB) as
models/<run_root's name>_s<seed>_<stage>; commit it. A later stage starts from that directory when the run is gone,
so a fresh machine (ten times, sessions 21-53) loses the data, not the training: it regenerates the data and goes on
from the last kept stage. Since session 60 it need not lose the data either: `pack` keeps the features of every solved
episode (learn.packs, ~0.1 MB an episode against ~0.9 MB and ~18 s of FEA) in the repository's packs/, and every
command first puts them in place (<out>/features/), where learn reads them and `data` counts them as solved.
`park` does for a paused stage what `keep` does for a finished one: its run's last.pt (optimiser, history and split
with it: resumable) copied to <park_dir>/<run_root's name>_s<seed>_<stage>.pt (~21 MB a seed; commit it), and every
`train` or `status` puts a parked checkpoint back as its run's last.pt where the run is gone, so a stage of more
epochs than a session leaves time for (ft2: ~135 min, of which data and evaluations take a session's first hour)
goes on from its last epoch on a fresh machine too. `park` also deletes a parked file whose stage has finished since
(commit the deletion).
`status` prints where both seeds and the data stand.
`--set key=value` (repeatable; make RECORD_SET="...") overrides a key of the conf for any command: with `stage_args`
(appended to every stage's learn.train args) and its own `run_root` (its runs, keeps, parks and logs are named after
it) another chain of the same stages runs beside the default one, e.g. one pass (session 64):
    make record RECORD_SET="run_root=runs/record1p stage_args=[model.passes=1] publish_as=record1p_pair"
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from omegaconf import OmegaConf  # noqa: E402

from fea_factory.generate import REFUSALS, WRITTEN, Manifest, episode_path  # noqa: E402
from learn.packs import packed  # noqa: E402
from learn.publish import CARD, is_published  # noqa: E402

CONF = ROOT / "conf" / "record.yaml"
MIN_STAGE_MIN = 5.0  # a stage is not started with less than this left of the budget, nor with less than one epoch
EPOCH_MARGIN = 1.1  # ... of it: learn.train always trains one epoch before it looks at its time limit (epoch_minutes)
POLL_S = 60.0  # --wait: seconds between looks at the manifests while a stage's data are being generated
WAITS = 4  # exit code: the next stage's data are not complete (not a failure: generate them, then the same command)
OUTCOMES = {0: "every stage finished", 3: "paused (budget): run the same command again to go on",
            WAITS: "waits for data: make record-data, then the same command again"}


def conf(path: Path = CONF, overrides: list[str] | None = None):
    """conf/record.yaml (or `path`) with `overrides` (OmegaConf dotlist, key=value) on top: another chain of the same
    stages, e.g. run_root=runs/record1p 'stage_args=[model.passes=1]' publish_as=record1p_pair (keeps and parks named
    after run_root, so it never touches the default chain's)."""
    cfg = OmegaConf.load(path)
    for item in overrides or []:
        if "=" not in item or item.split("=", 1)[0] not in cfg:
            raise ValueError(f"--set {item!r}: must be <key>=<value> with a top-level key of {path.name} "
                             f"({', '.join(str(k) for k in cfg)})")
    return OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides or [])))


def missing_episodes(entry, n: int | None = None) -> list[int]:
    """Indices of `entry`'s range (its first `n` only, if given) with no record of a written episode (solved, or a
    whole file a killed generator left, recorded as skipped) or a refusal, in its manifest or its feature packs."""
    done = Manifest(ROOT / entry.out / "manifest.jsonl").episodes_with_status(*WRITTEN, *REFUSALS)
    done |= {int(r["episode"]) for r in packed_records(ROOT / entry.out) if r.get("status") in (*WRITTEN, *REFUSALS)}
    return sorted(set(range(int(entry.start), int(entry.start) + int(entry.n if n is None else n))) - done)


def packed_records(data_dir: Path) -> list[dict]:
    """The manifest records kept with the feature packs of a data directory (learn.packs: <data_dir>/features/)."""
    from learn.packs import pack_manifest, pack_paths

    return [r for p in pack_paths(data_dir) for r in pack_manifest(p)]


def repo_packs(cfg, entry) -> Path:
    """Where the repository keeps the feature packs of a data entry: <pack_dir>/<the entry's directory name>."""
    return ROOT / cfg.pack_dir / Path(str(entry.out)).name


def restore(cfg) -> None:
    """The repository's feature packs of every data entry put in its data directory (<out>/features/), so learn
    reads them and missing_episodes counts them: what a session packed is not solved again on a fresh machine."""
    from learn.packs import pack_dir

    if not cfg.get("pack_dir"):
        return  # a record conf without packs
    for e in cfg.data:
        for src in sorted(repo_packs(cfg, e).glob("*.h5")):
            if copied(src, pack_dir(ROOT / e.out) / src.name):
                print(f"[record] {e.out}: feature pack {src} in place", flush=True)


def copied(src: Path, dst: Path) -> bool:
    """dst made a copy of src (atomically: a killed copy leaves dst as it was) unless it already is one; whether it
    was copied."""
    import shutil

    from data_schema import atomic

    if dst.exists() and dst.read_bytes() == src.read_bytes():
        return False
    with atomic.replacing(dst) as tmp:
        shutil.copyfile(src, tmp)
    return True


def runs_of(indices: list[int]) -> list[tuple[int, int]]:
    """Sorted indices as (start, n) runs of consecutive ones: [3, 4, 5, 9] -> [(3, 3), (9, 1)]."""
    runs: list[list[int]] = []
    for i in indices:
        if runs and i == runs[-1][0] + runs[-1][1]:
            runs[-1][1] += 1
        else:
            runs.append([i, 1])
    return [(a, b) for a, b in runs]


def needs(cfg, stage) -> dict[str, int]:
    """{data out: how many of its first episodes} the stage trains on: its `needs`, or every episode of `data`."""
    entries = {e.out: int(e.n) for e in cfg.data}
    asked = dict(stage.get("needs") or entries)
    for out, n in asked.items():
        if out not in entries:
            raise ValueError(f"stage {stage.name}: needs {out!r}, which is not one of data's outs {sorted(entries)}")
        if not 1 <= int(n) <= entries[out]:
            raise ValueError(f"stage {stage.name}: needs {out}: {n}; must be 1..{entries[out]} (its data entry's n)")
    return {out: int(n) for out, n in asked.items()}


def data_short(cfg, stage) -> dict[str, int]:
    """{data out: episodes still missing} of what the stage needs; empty when it may start."""
    by_out = {e.out: e for e in cfg.data}
    return {out: k for out, n in needs(cfg, stage).items() if (k := len(missing_episodes(by_out[out], n)))}


def lacking(short: dict[str, int]) -> str:
    """data_short's {out: missing} as 'data/ds_large lacks 12, data/ds_val lacks 100 episodes'."""
    return ", ".join(f"{k} lacks {v}" for k, v in short.items()) + " episodes"


def stage_state(run_dir: Path, kept: Path | None = None) -> tuple[str, float]:
    """('finished' | 'paused' | 'new' | 'kept', minutes of training done) of one stage's run; 'kept': no run on this
    machine, but the stage's published directory `kept` (a finished stage, as good as one for what follows)."""
    import torch

    last = ROOT / run_dir / "last.pt"
    if not last.exists():
        if kept is not None and is_published(ROOT / kept):
            card = json.loads((ROOT / kept / CARD).read_text())
            return "kept", float(card["members"][0].get("training_seconds") or 0.0) / 60
        return "new", 0.0
    ckpt = torch.load(last, map_location="cpu", weights_only=True)
    minutes = float((ckpt.get("history") or [{}])[-1].get("seconds", 0.0)) / 60
    return ("finished" if ckpt.get("finished") else "paused"), minutes


def run_dir(cfg, seed: int, name: str) -> Path:
    """Relative to the repository (the commands run there; checkpoints record the paths they were given)."""
    return Path(f"{cfg.run_root}_s{seed}") / name


def kept_dir(cfg, seed: int, stage) -> Path | None:
    """Where a stage with `keep` is published (models/record_s0_ref18); None for a stage that is not kept."""
    if not stage.get("keep"):
        return None
    return Path(cfg.get("keep_dir", "models")) / stage_label(cfg, seed, stage)


def stage_label(cfg, seed: int, stage) -> str:
    """A seed's stage as the repository names what it keeps of it: <run_root's name>_s<seed>_<stage> (record_s0_ft2)."""
    return f"{chain_name(cfg)}_s{seed}_{stage.name}"


def chain_name(cfg) -> str:
    """What a chain's keeps, parks and logs are named after: its run_root's last part (record)."""
    return Path(str(cfg.run_root)).name


def parked_path(cfg, seed: int, stage) -> Path | None:
    """Where `park` keeps a paused stage's last.pt (models/paused/record_s0_ft2.pt); None without a park_dir."""
    if not cfg.get("park_dir"):
        return None
    return Path(cfg.park_dir) / f"{stage_label(cfg, seed, stage)}.pt"


def park(cfg) -> int:
    """Every paused stage's last.pt -> its parked_path (when it differs); a parked file of a stage that has finished
    (or is kept) since is deleted. Commit park_dir."""
    if not cfg.get("park_dir"):
        raise ValueError(f"park: {CONF.name} needs park_dir (where paused stages are kept)")
    for seed in cfg.seeds:
        for stage in cfg.stages:
            parked, now = ROOT / parked_path(cfg, seed, stage), state(cfg, seed, stage)[0]
            if now == "paused" and copied(ROOT / run_dir(cfg, seed, stage.name) / "last.pt", parked):
                print(f"[record] seed {seed} {stage.name}: paused at {epochs_done(run_dir(cfg, seed, stage.name))}"
                      f"parked as {parked_path(cfg, seed, stage)} ({parked.stat().st_size / 2**20:.0f} MB): commit it",
                      flush=True)
            elif now in ("finished", "kept") and parked.exists():
                parked.unlink()
                print(f"[record] seed {seed} {stage.name}: {now}; its parked checkpoint deleted: commit the deletion "
                      f"(git add -A {cfg.park_dir})", flush=True)
    return 0


def unpark(cfg) -> None:
    """A parked checkpoint put back as its run's last.pt where the run has none and the stage is not kept: a paused
    stage resumes on a machine its run never was on."""
    if not cfg.get("park_dir"):
        return
    for seed in cfg.seeds:
        for stage in cfg.stages:
            parked = ROOT / parked_path(cfg, seed, stage)
            if parked.exists() and state(cfg, seed, stage)[0] == "new":  # no run here, nothing kept
                copied(parked, ROOT / run_dir(cfg, seed, stage.name) / "last.pt")
                print(f"[record] seed {seed} {stage.name}: {parked_path(cfg, seed, stage)} put back as its run's "
                      "last.pt", flush=True)


def state(cfg, seed: int, stage) -> tuple[str, float]:
    return stage_state(run_dir(cfg, seed, stage.name), kept_dir(cfg, seed, stage))


def source_of(cfg, source: str):
    """(the stage, the file) a `from` ('ref18/best.pt') names; a name of no stage, or a kept stage whose kept file
    is not this one (it would not carry the chain on), refused."""
    name, _, file = source.partition("/")
    stage = next((s for s in cfg.stages if s.name == name), None)
    if stage is None:
        raise ValueError(f"from {source!r} names no stage of {[s.name for s in cfg.stages]}")
    if stage.get("keep") and stage.keep != file:
        raise ValueError(f"from {source!r}, but stage {name} keeps {stage.keep!r}: keep the file the next stage "
                         "starts from")
    return stage, file


def start_of(cfg, seed: int, source: str) -> Path:
    """A stage's `from` ('ref18/best.pt'): that run's file, or when the run is gone, the stage's kept directory
    (published from that same file)."""
    stage, file = source_of(cfg, source)
    path = run_dir(cfg, seed, stage.name) / file
    kept = kept_dir(cfg, seed, stage)
    if not (ROOT / path).exists() and kept is not None and is_published(ROOT / kept):
        return kept
    return path


def keep(cfg, seed: int, stage) -> None:
    """Publish a finished stage's `keep` file as its kept directory, once (learn.publish: without the optimiser)."""
    kept = kept_dir(cfg, seed, stage)
    if kept is None or (ROOT / kept).exists():
        return
    cmd = [sys.executable, "-m", "learn.publish", f"checkpoints={run_dir(cfg, seed, stage.name) / stage.keep}",
           f"name={kept.name}", f"out_dir={kept.parent}"]  # run in the repository: the card's paths are relative
    print("[record]", " ".join(cmd), flush=True)
    subprocess.run(cmd, cwd=ROOT, check=True)
    print(f"[record] seed {seed} {stage.name}: kept as {kept}: commit it (git add {kept})", flush=True)


def trained(run_dir: Path, kept: Path | None = None) -> dict | None:
    """What a stage's training left: its run's last.pt, or with the run gone its kept member (history and split
    kept by learn.publish); None when neither exists."""
    import torch

    last = ROOT / run_dir / "last.pt"
    if not last.exists() and kept is not None and is_published(ROOT / kept):
        last = ROOT / kept / json.loads((ROOT / kept / CARD).read_text())["members"][0]["file"]
    return torch.load(last, map_location="cpu", weights_only=True) if last.exists() else None


def epoch_seconds(ckpt: dict) -> float | None:
    """Seconds of a checkpoint's last epoch (its history's training seconds count over all of its epochs)."""
    history = ckpt.get("history") or []
    if not history:
        return None
    return float(history[-1]["seconds"]) - (float(history[-2]["seconds"]) if len(history) > 1 else 0.0)


def designs_since(cfg, ckpt: dict) -> int:
    """Episodes the checkpoint's data_dir and train_extra_dirs hold, or will hold once `make record-data` has written
    what their data entries still miss, that its split does not name: the designs a stage starting from it with the
    same args adds to training (learn.train: new episodes join train). Counting the missing ones keeps the estimate
    whole while a fresh machine regenerates the data (session 59: ft2 shown at ~24 min an epoch, not ~34)."""
    dirs = [ckpt["config"]["data_dir"], *(ckpt["config"].get("train_extra_dirs") or [])]
    named = {n for names in ckpt["split"].values() for n in names}
    entries = {str(e.out): e for e in cfg.data}
    episodes = set()
    for d in dirs:
        episodes |= {p.name for p in (ROOT / d).glob("*.h5")} | set(packed(ROOT / d) if (ROOT / d).is_dir() else ())
        if str(d) in entries:
            episodes |= {episode_path(Path(d), i).name for i in missing_episodes(entries[str(d)])}
    return len(episodes - named)


def epoch_estimate(cfg, seed: int, stage) -> tuple[float, int] | None:
    """(minutes one epoch of `stage` is expected to take on this seed, epochs it has left): its own run's last epoch
    (a paused stage: its split is fixed), else the last epoch of the latest earlier stage trained with the same args
    (ft1's for ft2: the same recipe, the same epochs), times the training designs the stage will have over those that
    stage had (the data may have grown since: session 58's ds_large 300 -> 700; the validation's share of an epoch is
    scaled too, so an upper estimate); None when none has trained yet (the first stage; one unlike all before it)."""
    own = trained(run_dir(cfg, seed, stage.name), kept_dir(cfg, seed, stage))
    if own is not None and epoch_seconds(own):
        return epoch_seconds(own) / 60, int(own["config"]["epochs"]) - len(own["history"])
    names = [s.name for s in cfg.stages]
    for s in reversed([e for e in list(cfg.stages)[:names.index(stage.name)] if list(e.args) == list(stage.args)]):
        ckpt = trained(run_dir(cfg, seed, s.name), kept_dir(cfg, seed, s))
        if ckpt is not None and epoch_seconds(ckpt):
            n = len(ckpt["split"]["train"])
            return epoch_seconds(ckpt) * (n + designs_since(cfg, ckpt)) / n / 60, int(ckpt["config"]["epochs"])
    return None


def epoch_minutes(cfg, seed: int, stage) -> float | None:
    """epoch_estimate's minutes an epoch; None when nothing has trained that tells."""
    estimate = epoch_estimate(cfg, seed, stage)
    return None if estimate is None else estimate[0]


def minimum_minutes(cfg, seed: int, stage) -> float:
    """Budget a stage needs to be started: one expected epoch (with EPOCH_MARGIN), at least MIN_STAGE_MIN. A stage
    started on less would overrun the budget by most of an epoch (ft2 on 5 minutes left, session 57: ~25 min)."""
    return minimum_of(epoch_minutes(cfg, seed, stage))


def minimum_of(epoch: float | None) -> float:
    """minimum_minutes for an expected epoch of `epoch` minutes (None: not known)."""
    return max(MIN_STAGE_MIN, EPOCH_MARGIN * epoch) if epoch else MIN_STAGE_MIN


def data(cfg, jobs: int) -> int:
    """Every data entry's episodes that neither its manifest nor its feature packs hold, solved in runs of
    consecutive indices (fea_factory.generate: resumable; refusals stand), at most pack_part at a time, each batch
    packed as soon as it is solved (`pack`: a session that ends mid-entry leaves at most one batch unpacked)."""
    step = int(cfg.get("pack_part") or 0) if cfg.get("pack_dir") else 0
    for entry in cfg.data:
        missing = missing_episodes(entry)
        if not missing:
            print(f"[record] {entry.out}: all {entry.n} episodes solved, packed or refused", flush=True)
        for start, n in runs_of(missing):
            for a in range(start, start + n, step or n):
                b = min(start + n, a + (step or n))
                cmd = [sys.executable, "-m", "fea_factory.generate", f"n={b - a}", f"start={a}",
                       f"out={entry.out}", f"jobs={jobs}", "np=1", *entry.args]
                print("[record]", " ".join(cmd), flush=True)
                rc = subprocess.call(cmd, cwd=ROOT)
                if step:
                    pack(cfg)
                if rc:
                    return rc
    return 0


def pack(cfg) -> int:
    """Every data entry's solved episodes (and refusals) that no repository pack holds yet -> new feature packs of
    at most cfg.pack_part episodes in <pack_dir>/<the entry's directory name>/part_<first>-<last>.h5 (earlier parts
    are never rewritten: git keeps each once); then put in place (restore). Commit them."""
    from learn.dataset import load_features
    from learn.packs import pack_manifest, write_pack

    if not cfg.get("pack_dir") or int(cfg.get("pack_part") or 0) < 1:
        raise ValueError(f"pack: {CONF.name} needs pack_dir (where packs are kept) and pack_part >= 1 (episodes a part)")
    for e in cfg.data:
        out, held = ROOT / e.out, repo_packs(cfg, e)
        packed_already = {int(r["episode"]) for p in sorted(held.glob("*.h5")) for r in pack_manifest(p)}
        latest = {int(r["episode"]): r for r in Manifest(out / "manifest.jsonl").records()}  # the last record wins
        todo = []
        for i in range(int(e.start), int(e.start) + int(e.n)):
            r = latest.get(i)
            if i in packed_already or r is None or r.get("status") not in (*WRITTEN, *REFUSALS):
                continue
            if r["status"] in WRITTEN and not episode_path(out, i).is_file():
                print(f"[record] {e.out}: episode {i} is on record as written but its file is gone; not packed "
                      "(make record-data solves it again)", file=sys.stderr)
                continue
            todo.append(i)
        for k in range(0, len(todo), int(cfg.pack_part)):
            chunk = todo[k:k + int(cfg.pack_part)]
            written = [i for i in chunk if latest[i]["status"] in WRITTEN]
            features = load_features([episode_path(out, i) for i in written])
            path = held / f"part_{chunk[0]:05d}-{chunk[-1]:05d}.h5"
            write_pack(path, features, [latest[i] for i in chunk])
            print(f"[record] {e.out}: {len(written)} episodes and {len(chunk) - len(written)} refusals -> "
                  f"{path} ({path.stat().st_size / 2**20:.1f} MB)", flush=True)
    restore(cfg)
    return 0


def train(cfg, seed: int, budget_min: float, wait: bool = False) -> int:
    """One seed's stages in order within `budget_min` minutes; `wait`: a stage whose data are not complete waits
    for them (polled every POLL_S seconds, while the budget leaves a stage's minimum) instead of exiting WAITS."""
    deadline = time.monotonic() + 60 * budget_min
    for stage in cfg.stages:
        needs(cfg, stage)  # a bad `needs` or `from` refused before anything runs
        if stage["from"] is not None:
            try:
                source_of(cfg, stage["from"])
            except ValueError as e:
                raise ValueError(f"stage {stage.name}: {e}") from None
    for stage in cfg.stages:
        rd = run_dir(cfg, seed, stage.name)
        now, done = state(cfg, seed, stage)
        if now in ("finished", "kept"):
            print(f"[record] seed {seed} {stage.name}: {now} ({done:.0f} min)", flush=True)
            if now == "finished":
                keep(cfg, seed, stage)
            continue
        short = data_short(cfg, stage)
        minimum = minimum_minutes(cfg, seed, stage)
        if short and wait:  # poll while the generator (make record-data, running beside) finishes them
            print(f"[record] seed {seed} {stage.name}: waiting for its data ({lacking(short)}), every "
                  f"{POLL_S:.0f} s", flush=True)
            while short and (deadline - time.monotonic()) / 60 >= minimum:
                time.sleep(POLL_S)
                short = data_short(cfg, stage)
        if short:
            print(f"[record] seed {seed} {stage.name}: its data are not complete: {lacking(short)}; run make "
                  "record-data first", file=sys.stderr)
            return WAITS
        minimum = minimum_minutes(cfg, seed, stage)  # again: the designs a wait saw arrive lengthen the epoch
        left = (deadline - time.monotonic()) / 60
        if left < minimum:
            print(f"[record] seed {seed}: budget spent before {stage.name} ({left:.0f} min left, {minimum:.0f} needed: "
                  "one epoch of it); run the same command again to go on")
            return 3
        start = [] if stage["from"] is None else [f"init_from={start_of(cfg, seed, stage['from'])}"]
        cmd = [sys.executable, "-m", "learn.train", *stage.args, *cfg.get("stage_args", []), *start, f"seed={seed}",
               f"run_dir={rd}",
               f"time_limit_min={done + left:.1f}"]
        print(f"[record] seed {seed} {stage.name} ({now}, {done:.0f} min done):", " ".join(cmd), flush=True)
        rc = subprocess.call(cmd, cwd=ROOT)
        if rc:
            return rc
        now, done = state(cfg, seed, stage)
        if now == "finished":
            keep(cfg, seed, stage)
        else:
            print(f"[record] seed {seed} {stage.name} paused at {done:.0f} min (budget); run the same command again "
                  "to go on")
            return 3
    print(f"[record] seed {seed}: every stage finished; its member: {run_dir(cfg, seed, cfg.stages[-1].name)}/last.pt")
    return 0


def side_by_side(cfg, conf_path: Path, seeds: list[int], budget_min: float, log_dir: Path,
                 wait: bool = False, overrides: list[str] = ()) -> int:
    """Every seed's chain at once, one process (one core) each, each writing log_dir/<run_root's name>_s<seed>.log."""
    log_dir.mkdir(parents=True, exist_ok=True)
    procs = []
    for seed in seeds:
        log = log_dir / f"{chain_name(cfg)}_s{seed}.log"
        with open(log, "a") as out:
            procs.append((seed, log, subprocess.Popen(
                [sys.executable, __file__, "train", "--seed", str(seed), "--budget-min", str(budget_min),
                 "--conf", str(conf_path), *(["--wait"] if wait else []), *(f"--set={o}" for o in overrides)],
                cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)))
        print(f"[record] seed {seed}: started (pid {procs[-1][2].pid}), log {log}", flush=True)
    codes = {seed: p.wait() for seed, _, p in procs}
    for seed, log, _ in procs:
        print(f"[record] seed {seed}: {OUTCOMES.get(codes[seed], f'failed (exit {codes[seed]}): see {log}')}")
    failed = [c for c in codes.values() if c not in OUTCOMES]
    return failed[0] if failed else max(codes.values())


def members(cfg) -> list[str]:
    return [str(run_dir(cfg, s, cfg.stages[-1].name) / "last.pt") for s in cfg.seeds]


def epochs_done(run_dir: Path) -> str:
    """'epoch 8 of 18' for a started run (its last.pt), '' for none."""
    import torch

    last = ROOT / run_dir / "last.pt"
    if not last.exists():
        return ""
    ckpt = torch.load(last, map_location="cpu", weights_only=True)
    return f"epoch {len(ckpt.get('history') or [])} of {(ckpt.get('config') or {}).get('epochs')}, "


def status(cfg) -> int:
    for e in cfg.data:
        in_packs = len(packed_records(ROOT / e.out))
        print(f"{e.out}: {int(e.n) - len(missing_episodes(e))} of {e.n} episodes done" + (
            f" ({in_packs} of them in the repository's feature packs, {repo_packs(cfg, e)})"
            if cfg.get("pack_dir") else ""))
    states = {(seed, s.name): state(cfg, seed, s) for seed in cfg.seeds for s in cfg.stages}  # each checkpoint once
    done = ("finished", "kept")
    for seed in cfg.seeds:
        print(f"seed {seed}: " + ", ".join(
            f"{s.name} {st} ({epochs_done(run_dir(cfg, seed, s.name)) if st == 'paused' else ''}{m:.0f} min)"
            for s in cfg.stages for st, m in [states[seed, s.name]]))
        upcoming = next((s for s in cfg.stages if states[seed, s.name][0] not in done), None)
        if upcoming is not None and (estimate := epoch_estimate(cfg, seed, upcoming)) is not None:
            epoch, left = estimate
            print(f"seed {seed} next: {upcoming.name}, ~{epoch:.0f} min an epoch x {left} epochs left = "
                  f"~{epoch * left:.0f} min (a budget under {minimum_of(epoch):.0f} min does not start it)")
    for s in cfg.stages:
        if all(states[seed, s.name][0] in done for seed in cfg.seeds):
            print(f"stage {s.name}: done by every seed")  # data added since are for the stages after it
            continue
        short = data_short(cfg, s)
        print(f"stage {s.name}: " + ("its data are complete" if not short else "waits for " + ", ".join(
            f"{k} ({v} missing of its first {needs(cfg, s)[k]})" for k, v in short.items())))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=("data", "train", "status", "members", "pack", "park", "publish-name"))
    p.add_argument("--seed", type=int, default=None, help="one seed's chain; default: every seed side by side")
    p.add_argument("--log-dir", type=Path, default=ROOT / "logs", help="side by side: <run_root's name>_s<seed>.log here (record_s<seed>.log)")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--budget-min", type=float, default=150.0, help="minutes this invocation may train")
    p.add_argument("--conf", type=Path, default=CONF)
    p.add_argument("--wait", action="store_true", help="train: a stage whose data are not complete waits for them "
                   "(make record-data running beside) within the budget, instead of exiting 4")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a top-level key of the conf (repeatable), e.g. --set run_root=runs/record1p")
    a = p.parse_args(argv)
    try:
        cfg = conf(a.conf, a.set)
    except ValueError as e:
        p.error(str(e))
    if a.what == "train" and a.seed is not None and a.seed not in list(cfg.seeds):
        p.error(f"--seed {a.seed}: conf/record.yaml's seeds are {list(cfg.seeds)}")
    if a.budget_min <= 0:
        p.error(f"--budget-min {a.budget_min}: must be > 0 minutes")
    if a.what not in ("members", "publish-name"):
        restore(cfg)  # the repository's feature packs in place before anything counts or reads episodes
    if a.what in ("train", "status"):
        unpark(cfg)  # a paused stage's parked checkpoint where its run is gone
    if a.what == "data":
        return data(cfg, a.jobs)
    if a.what == "pack":
        return pack(cfg)
    if a.what == "park":
        return park(cfg)
    if a.what == "train":
        if a.seed is None:
            return side_by_side(cfg, a.conf, [int(k) for k in cfg.seeds], a.budget_min, a.log_dir, a.wait, a.set)
        return train(cfg, a.seed, a.budget_min, a.wait)
    if a.what == "members":
        print(",".join(members(cfg)))
        return 0
    if a.what == "publish-name":
        print(cfg.publish_as)
        return 0
    return status(cfg)


if __name__ == "__main__":
    sys.exit(main())
