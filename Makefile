# Two set-up commands: `make demo` and `make test`. Both install what is missing first.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench model atoms clean-venv

$(STAMP): pyproject.toml requirements.lock scripts/setup_env.sh
	PY=$(PY) VENV=$(VENV) bash scripts/setup_env.sh
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/blsm demo --out out/demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_forward.py --out docs/benchmarks.md

# Rebuild the packaged model from Anny (about 2 minutes; the first Anny load compiles kernels).
model: $(STAMP)
	$(BIN)/blsm build-anny --out blsm/data/blsm_anny_v1.npz

atoms: $(STAMP)
	$(BIN)/blsm atoms --out out/atoms

clean-venv:
	rm -rf $(VENV)
