# Every target makes and uses .venv at the repo root.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= outputs/quickstart
CKPT_OUT ?= outputs/checkpoint_demo
WHEELS ?= wheels
# the fast tier's pytest workers (pytest-xdist): one per core, at most 4; TEST_WORKERS=0 runs it in one process
TEST_WORKERS ?= auto
# the int8 bench's model: the newest demo run's best checkpoint (by time: by name version_8 sorts after version_10)
INT8_CKPT ?= $(firstword $(shell ls -t $(OUT)/tensorboard/version_*/checkpoints/best-*.ckpt 2>/dev/null))

.PHONY: install demo test test-all bench bench-gpu wheels install-offline lint clean

$(STAMP): pyproject.toml constraints.txt
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip
	$(BIN)/pip install -c constraints.txt -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

# CKPT=models/dapm-synthetic-r18-256 (or any checkpoint): test that model instead of training one;
# DEMO_ARGS="--train-size 6000 --max-epochs 10": the longer training measured in docs/transfer.md (about 14 min on 2 cores)
demo: $(STAMP)
	$(BIN)/python -m dapm_lightning.tools.quickstart $(if $(CKPT),--out $(CKPT_OUT) --checkpoint $(CKPT),--out $(OUT)) $(DEMO_ARGS)

test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --maxprocesses 4

test-all: test  # the README's fast tier first, then the slow tier (in one process: its tests start their own)
	$(BIN)/python -m pytest -q -m slow --durations=20

# benchmarks/ beside the package (not in the wheel), run from the repository root
bench: $(STAMP)
	$(BIN)/python -m benchmarks.bench
	$(BIN)/python -m benchmarks.bench_synth speed
	$(BIN)/python -m benchmarks.bench_predict speed --rounds 3
	$(BIN)/python -m benchmarks.bench_fit_memory
	@if [ -n "$(INT8_CKPT)" ]; then $(BIN)/python -m benchmarks.bench_predict int8 --ckpt_path "$(INT8_CKPT)"; \
	else echo "bench_predict int8: no trained checkpoint in $(OUT) (make demo, or INT8_CKPT=FILE)"; fi

# the GPU kit (docs/gpu.md): one command, <= 9 minutes on one GPU; BENCH_GPU_ARGS="--device cpu --tiny" checks it
bench-gpu: $(STAMP)
	$(BIN)/python -m benchmarks.bench_gpu $(BENCH_GPU_ARGS)

# air-gapped GPU nodes (docs/gpu.md): wheels of everything but the node's PyTorch stack, then install from them;
# WHEELS_TARGET="--python-version 3.10 --platform manylinux2014_x86_64" collects for another Python
wheels:
	mkdir -p $(WHEELS)
	$(PYTHON) scripts/offline_requirements.py > $(WHEELS)/requirements.txt
	$(PYTHON) -m pip download --dest $(WHEELS) --only-binary=:all: $(WHEELS_TARGET) -c constraints.txt \
		-r $(WHEELS)/requirements.txt
	$(PYTHON) -m pip wheel --no-deps --no-build-isolation --wheel-dir $(WHEELS) .

install-offline:
	$(PYTHON) -m pip install --no-index --find-links $(WHEELS) "dapm-lightning[export]"

lint: $(STAMP)
	$(BIN)/ruff check dapm_lightning tests benchmarks
	$(BIN)/mypy

clean:
	rm -rf $(VENV) outputs .pytest_cache
