# Two set-up commands: `make demo` and `make test`. Both install what is missing first.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench model learned-model atoms motions prior clean-venv

$(STAMP): pyproject.toml requirements.lock scripts/setup_env.sh
	PY=$(PY) VENV=$(VENV) bash scripts/setup_env.sh
	touch $(STAMP)

# 64 labelled images with the embedded defaults (re-running continues or keeps the same dataset),
# checked, and their contact sheet; plus a sheet of random BLSM bodies.
demo: $(STAMP)
	$(BIN)/synth generate - --out out/demo/dataset --num 64 --workers 2 --resume
	$(BIN)/synth validate out/demo/dataset
	$(BIN)/synth preview out/demo/dataset --out out/demo/contact_sheet.png --count 16
	$(BIN)/blsm demo --out out/demo/bodies

test: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

# Long: the generator part makes about 2000 images (about 40 minutes on 2 cores).
bench: $(STAMP)
	$(BIN)/python benchmarks/bench_forward.py --out docs/benchmarks.md
	$(BIN)/python benchmarks/bench_synth.py --out docs/benchmarks.md

# Rebuild the packaged model from Anny (about 2 minutes; the first Anny load compiles kernels).
model: $(STAMP)
	$(BIN)/blsm build-anny --out blsm/data/blsm_anny_v1.npz

# The model learnt from scans (thesis Sec. 5.4): 1000 Anny stand-in subjects, registration,
# learning, SMPL-reimpl and the held-out evaluation into docs/ (hours on 2 cores; resumable).
learned-model: $(STAMP)
	$(BIN)/blsm train configs/blsm/train_default.yaml --out out/train/blsm_learned.npz --overwrite

atoms: $(STAMP)
	$(BIN)/blsm atoms --out out/atoms

# Import the shared CMU clips (about 12 minutes on 2 cores), preview a walk, a dance and a jump.
MOCAP ?= ../shared/mocap/cmu
motions: $(STAMP)
	$(BIN)/blsm mocap import $(MOCAP) --out out/motions --fps 30 --overwrite
	$(BIN)/blsm mocap preview out/motions/007_01.npz --out out/motions/preview_walk_007_01.png
	$(BIN)/blsm mocap preview out/motions/005_02.npz --out out/motions/preview_dance_005_02.png
	$(BIN)/blsm mocap preview out/motions/002_04.npz --out out/motions/preview_jump_002_04.png

# Refit the packaged pose prior from out/motions (two clips held out for the tests).
prior: $(STAMP)
	$(BIN)/blsm mocap fit-prior out/motions --out blsm/data/pose_prior_cmu.npz --exclude 007_12 005_20

clean-venv:
	rm -rf $(VENV)
