# Set-up and main jobs. `make test` and `make demo` create .venv if missing and install
# everything they need (torch==2.13.0 first when no torch is present, so pip never pulls a
# multi-GB CUDA build), then run.
VENV    ?= .venv
PY      := $(VENV)/bin/python
EXTRAS  ?= render,eval,export,openvino,scale,dev
PYTEST_ARGS ?=

.PHONY: setup test demo lint clean-cache

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[$(EXTRAS)]"
	touch $@

setup: $(VENV)/.installed
	@bash scripts/setup_llvm.sh

test: setup
	$(PY) -m pytest -q $(PYTEST_ARGS)

# The whole pipeline on the simulated demo dataset (render, teacher, distilled and no-KD
# students, evaluation, benchmark): reports/demo/. About 30 minutes on 2 CPU cores.
demo: setup
	VENV=$(VENV) bash scripts/demo.sh

lint: setup
	$(VENV)/bin/ruff check denoiser tests train.py
