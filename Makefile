# Every target makes and uses .venv at the repo root.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= outputs/quickstart

.PHONY: install demo test test-all bench lint clean

$(STAMP): pyproject.toml constraints.txt
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip
	$(BIN)/pip install -c constraints.txt -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m dapm_lightning.tools.quickstart --out $(OUT)

test: $(STAMP)
	$(BIN)/python -m pytest -q

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -m ""

bench: $(STAMP)
	$(BIN)/python -m dapm_lightning.tools.bench
	$(BIN)/python -m dapm_lightning.tools.bench_synth speed
	$(BIN)/python -m dapm_lightning.tools.bench_predict speed --rounds 3

lint: $(STAMP)
	$(BIN)/ruff check dapm_lightning tests
	$(BIN)/mypy

clean:
	rm -rf $(VENV) outputs .pytest_cache
