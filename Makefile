# morphsim: `make help` lists the targets.
PY      ?= .venv/bin/python
NP      ?= 1
JOBS    ?= 1
N       ?= 8
OUT     ?= data/episodes
PANEL   ?= reduced
# make tradeoff writes to reports/tradeoff unless OUT= is given on the command line
TRADEOFF_OUT = $(if $(filter command line,$(origin OUT)),$(OUT),reports/tradeoff)
MPIRUN  := OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 mpirun
export OMPI_ALLOW_RUN_AS_ROOT=1
export OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
export OMP_NUM_THREADS ?= 1

.PHONY: help setup test test-slow test-mpi designs mesh-demo solve-demo dataset reference-data large-data validate fingerprint bench-fea stability bench-rollout tradeoff train evaluate reference-train finetune reference-evaluate publish record-data record record-pack record-park record-status record-evaluate compare validity-calibration curves diagnose predict sweep learned-extremes clean

help:  ## list the targets
	@grep -E '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-12s %s\n", $$1, $$2}'

setup:  ## install Debian packages (FEniCSx, gmsh, MPI, OpenBLAS) and the .venv (idempotent)
	bash scripts/setup.sh

test:  ## fast test suite (CI)
	$(PY) -m pytest -q -m "not slow"

test-slow:  ## slow verification tests (mesh convergence, large rotation, extremes)
	$(PY) -m pytest -q -m slow

designs:  ## sample N designs into data/designs
	$(PY) -m fea_factory.sample n=$(N) out=data/designs

solve-demo:  ## solve one sampled design (NP ranks) into data/demo.h5
	$(PY) -m fea_factory.sample n=1 out=data/demo
	$(MPIRUN) -n $(NP) $(PY) -m fea_factory.solve design=data/demo/design_00000.json out=data/demo.h5

dataset:  ## generate N episodes into OUT (JOBS in parallel, NP MPI ranks each); resumable (episodes refused for contact or divergence are not solved again under the same settings: ARGS=retry_refused=true)
	$(PY) -m fea_factory.generate n=$(N) out=$(OUT) jobs=$(JOBS) np=$(NP) $(ARGS)

REF_N ?= 400
reference-data:  ## the README's learned-simulator data: data/ds_heldout (50 new designs, first: ~16 min, so evaluations over all 102 held-out designs can start) + data/ds_default (REF_N=400; 800 since session 17); resumable; JOBS=2: ~210-250 episodes/h
	$(PY) -m fea_factory.generate n=50 start=100000 out=data/ds_heldout jobs=$(JOBS) np=1
	$(PY) -m fea_factory.generate n=$(REF_N) out=data/ds_default jobs=$(JOBS) np=1

LARGE_N ?= 200
large-data:  ## extra large training designs (conf/grid/large.yaml) -> data/ds_large, indices from 200000 so names never meet ds_default's; resumable
	$(PY) -m fea_factory.generate n=$(LARGE_N) start=200000 grid=large out=data/ds_large jobs=$(JOBS) np=1

VAL_N ?= 100
validation-data:  ## extra validation designs for learn.train val_extra_dirs (never trained on, never in the 102 evaluated) -> data/ds_val, indices from 300000; resumable
	$(PY) -m fea_factory.generate n=$(VAL_N) start=300000 out=data/ds_val jobs=$(JOBS) np=1

validate:  ## validate every episode in OUT
	$(PY) -m data_schema.validate $(OUT)

FP ?= conf/held_out/ds_default_fingerprint.csv
fingerprint:  ## is OUT the data a result was measured on? checks OUT against FP (WRITE=1: write FP from OUT instead)
	$(PY) -m data_schema.fingerprint $(OUT) $(if $(WRITE),--write,--check) $(FP)

train:  ## train the Double GN on the episodes in OUT (resumes runs/train/last.pt)
	$(PY) -m learn.train data_dir=$(OUT)

evaluate:  ## roll out the trained model on the held-out split; report in runs/evaluate/
	$(PY) -m learn.evaluate data_dir=$(OUT)

reference-train:  ## the full-scale reference training (conf/experiment/reference.yaml; data from make reference-data; 2.2 h on one core for the [256, 128] default, session 36's runs/s36_ref348_e32; resumable)
	$(PY) -m learn.train +experiment=reference $(ARGS)

RUN ?= runs/finetune
finetune:  ## carry CKPT on to every training design of data/ds_default + data/ds_large, monitored on data/ds_val too (conf/experiment/finetune.yaml; 4 epochs, ~46 min on one core at 945 designs; resumable) -> RUN
	@test -n "$(CKPT)" || { echo "make finetune: CKPT=runs/<start>/best.pt (the trained start) is required" >&2; exit 2; }
	$(PY) -m learn.train +experiment=finetune "init_from=$(CKPT)" run_dir=$(RUN) $(ARGS)

REF ?= reports/reference
reference-evaluate:  ## CKPT (or CKPT='[a.pt,b.pt]', an ensemble) on the 102 held-out designs: 52 pinned of data/ds_default + data/ds_heldout -> REF/102 (REF=reports/reference; timed as deployed: BACKEND=aot_tuned since session 52, kernels picked by timing, 3-5 min more to compile a new model; BACKEND=aot as in sessions 38-51)
	$(PY) -m learn.evaluate "checkpoint=$(or $(CKPT),runs/reference/best.pt)" data_dir=data/ds_default split=val+test plots=false threads=1 rollout_backend=$(or $(BACKEND),aot_tuned) out_dir=$(REF)/52 $(ARGS)
	$(PY) -m learn.evaluate "checkpoint=$(or $(CKPT),runs/reference/best.pt)" data_dir=data/ds_heldout split=all timing_repeats=1 plots=false threads=1 rollout_backend=$(or $(BACKEND),aot_tuned) out_dir=$(REF)/fresh $(ARGS)
	$(PY) -m learn.combine 'reports=[$(REF)/52,$(REF)/fresh]' out_dir=$(REF)/102

publish:  ## keep a trained model in the repository: CKPT (or CKPT='[a.pt,b.pt]', an ensemble) -> models/NAME/ + card.json (REPORT=its report dir, e.g. reports/x/102: figures on the card); commit it; CKPT=models/NAME works wherever a checkpoint is read
	@test -n "$(CKPT)" -a -n "$(NAME)" || { echo "make publish: CKPT=runs/<run>/best.pt (or '[a.pt,b.pt]') and NAME=<name> are required" >&2; exit 2; }
	$(PY) -m learn.publish "checkpoints=$(CKPT)" name=$(NAME) $(if $(REPORT),report=$(REPORT)) $(ARGS)

# RECORD_SET="key=value ..." (any record-* target): another chain of conf/record.yaml's stages, e.g. one pass:
#   RECORD_SET="run_root=runs/record1p stage_args=[model.passes=1] publish_as=record1p_pair"
RECORD_SET_ARGS = $(foreach o,$(RECORD_SET),--set=$(o))
record-data:  ## every episode the record chain trains and is evaluated on (conf/record.yaml: ds_heldout 50, ds_default 800, ds_large 700, ds_val 100; ~6 h on 2 cores) that no feature pack in packs/ holds (put in place first), packed every 200 as solved (commit packs/); JOBS=2; resumable
	$(PY) scripts/record.py data --jobs $(JOBS) $(RECORD_SET_ARGS)

record:  ## the record model rebuilt on a fresh machine (conf/record.yaml): every seed's stages in order, side by side (one core each; SEED=k: one alone), each resumable and started once the data it needs exist, for at most BUDGET_MIN minutes (150; logs/record_s<k>.log; WAIT=1: a stage waits for its data, make record-data running beside, instead of exiting 4); again each session until finished; kept stages land in models/record_s<k>_<stage> (commit them)
	$(PY) scripts/record.py train $(if $(SEED),--seed $(SEED)) --budget-min $(or $(BUDGET_MIN),150) $(if $(WAIT),--wait) $(RECORD_SET_ARGS)

record-pack:  ## the features of every episode record-data solved that packs/ lacks (learn.packs; ~0.1 MB an episode) -> new packs/<data dir>/part_<first>-<last>.h5: commit them, and a fresh machine's record-data solves only what they lack
	$(PY) scripts/record.py pack $(RECORD_SET_ARGS)

record-park:  ## every paused stage's last.pt (resumable) -> models/paused/record_s<k>_<stage>.pt, before a session ends: commit it, and the next session's make record resumes it on any machine (a finished stage's parked file is deleted: commit that too)
	$(PY) scripts/record.py park $(RECORD_SET_ARGS)

record-status:  ## where the record chain stands: episodes generated, each seed's stages (new / paused / finished / kept), which stages' data are complete
	$(PY) scripts/record.py status $(RECORD_SET_ARGS)

record-evaluate:  ## the record pair (each seed's last stage) on the 102 held-out designs -> reports/<publish_as>/102, then published as models/<publish_as> (record_pair; commit it)
	members=$$($(PY) scripts/record.py members $(RECORD_SET_ARGS)) && name=$$($(PY) scripts/record.py publish-name $(RECORD_SET_ARGS)) && \
	$(MAKE) reference-evaluate "CKPT=[$$members]" REF=reports/$$name && \
	$(MAKE) publish "CKPT=[$$members]" NAME=$$name REPORT=reports/$$name/102

compare:  ## design-by-design comparison of reports against the first (REPORTS=a,b[,c]; LABELS=x,y[,z]; SIZES=n1,n2,..: a scaling fit; reports/compare/)
	$(PY) -m learn.compare 'reports=[$(REPORTS)]' $(if $(LABELS),'labels=[$(LABELS)]') $(if $(SIZES),'sizes=[$(SIZES)]') out_dir=$(or $(CMP),reports/compare)

validity-calibration:  ## fit the validity thresholds to held-out reports (REPORTS=a,b; CHECK=c,d measured apart; reports/validity_calibration/)
	$(PY) -m learn.validity_calibration 'reports=[$(REPORTS)]' $(if $(CHECK),'check=[$(CHECK)]') out_dir=reports/validity_calibration

curves:  ## training curves of runs side by side, by epoch and by hour (RUNS=runs/a,runs/b; LABELS=x,y; reports/curves/)
	$(PY) -m learn.curves 'runs=[$(RUNS)]' $(if $(LABELS),'labels=[$(LABELS)]') out_dir=$(or $(CURVES),reports/curves)

diagnose:  ## where a checkpoint's error comes from: one-step vs rollout, train vs test (CKPT=runs/train/best.pt; runs/diagnose/)
	$(PY) -m learn.diagnose checkpoint=$(or $(CKPT),runs/train/best.pt)

predict:  ## learned morph of one design, no FEA (DESIGN=x.json CKPT=runs/train/best.pt; runs/predict/: ParaView view, verdict, png)
	$(PY) -m fea_factory.initial design=$(or $(DESIGN),$(OUT)/designs/episode_00000.json) out=runs/predict/initial.h5
	$(PY) -m learn.predict checkpoint=$(or $(CKPT),runs/train/best.pt) episode=runs/predict/initial.h5 out_dir=runs/predict

sweep:  ## Hydra multirun grid search over latent sizes and MLP widths (runs/sweep/results.csv)
	$(PY) -m learn.train -m +sweep=grid data_dir=$(OUT)

stability:  ## stability matrix at the extremes (reports/stability/; ~9 min)
	$(PY) scripts/stability_matrix.py --out reports/stability

bench-fea:  ## FEA benchmark table + plot (reports/bench_fea/)
	$(PY) scripts/bench_fea.py --out reports/bench_fea

bench-rollout:  ## learned rollout ms vs symmetry copies and designs per call, 1 thread (CKPT=runs/train/best.pt; BACKEND=torchscript,aot,aot_tuned; SETTINGS=1:false,..; reports/bench_rollout/; idle machine)
	$(PY) scripts/bench_rollout.py --checkpoint $(or $(CKPT),runs/train/best.pt) --batch $(or $(BATCH),8,32,128) \
		--backend $(or $(BACKEND),torchscript) $(if $(SETTINGS),--settings $(SETTINGS)) --out $(or $(BENCH),reports/bench_rollout)

tradeoff:  ## speed/accuracy trade (PANEL=reduced|full, CHECKPOINTS=a.pt,.., INSTALL=1: conf/solver/tradeoff_table.csv, RESUME=1)
	$(PY) scripts/tradeoff.py --panel $(PANEL) --out $(TRADEOFF_OUT) $(if $(CHECKPOINTS),--checkpoints $(CHECKPOINTS)) \
		$(if $(INSTALL),--install) $(if $(RESUME),--resume)

learned-extremes:  ## learned simulator on FEA designs outside its training ranges (CKPT=runs/train/best.pt; reports/learned_extremes/)
	$(PY) scripts/learned_extremes.py --checkpoint $(or $(CKPT),runs/train/best.pt) --out reports/learned_extremes --jobs $(JOBS)

clean:  ## remove generated data and reports (keeps .venv)
	rm -rf data reports outputs multirun .pytest_cache
