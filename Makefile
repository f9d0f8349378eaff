# Set-up and main jobs. `make test` and `make demo` create .venv if missing and install
# everything they need (torch==2.13.0 first when no torch is present, so pip never pulls a
# multi-GB CUDA build), then run.
VENV    ?= .venv
PY      := $(VENV)/bin/python
EXTRAS  ?= render,eval,export,openvino,scale,dev
PYTEST_ARGS ?=
# The suite runs in pytest-xdist worker processes, one per core (tests/conftest.py gives each worker's
# torch its share of the threads), long tests handed out first-come (worksteal): a test that kills its
# process (a native runtime's segfault) is reported as that test's failure, by name, the worker is
# replaced and the summary still prints (issue 44; tests/core/test_crash_isolation.py).
PYTEST_WORKERS ?= auto
PYTEST_ISOLATION ?= -p xdist -n $(PYTEST_WORKERS) --dist worksteal --max-worker-restart=100

.PHONY: gpu-check setup test demo readme readme-check ovext pareto compare ablations paper lint blender blender-val blender-venv release neon-tools

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[$(EXTRAS)]"
	touch $@

setup: $(VENV)/.installed
	@bash scripts/setup_llvm.sh

test: setup
	$(PY) -m pytest -q $(PYTEST_ISOLATION) $(PYTEST_ARGS)
	$(PY) scripts/readme_check.py --report-only

# Build the OpenVINO extension (denoiser/inference/ovext: one C++ header per operation) ahead of
# time into its cache ($$DENOISER_CACHE/ovext, else ~/.cache/denoiser/ovext), as a package
# maintainer or an image build would; without it, the first OpenVINO use builds it. Prints the
# library's path, or one line saying why it cannot be built (exit 1).
ovext: setup
	$(PY) -m denoiser.inference.ovext

# The pipelines (denoiser-pipeline over conf/pipeline/<name>.yaml: the stages, their skipping and
# resuming, the stage times in reports/<name>/timings.md). Keys go on the command line of
# denoiser-pipeline (denoiser-pipeline pipeline=demo 'seeds=[0,1,2,3,4]' jobs=2; --help lists them), or
# through ARGS here: make demo ARGS="'seeds=[0,1,2,3,4]'".
#   demo       render, teacher, distilled and no-KD students (3 seeds), evaluation, benchmark -> reports/demo
#   ablations  Fig. A.1 and the distillation ablations, after make demo -> reports/ablations
#   compare    Fig. A.2 / A.3 (NPPD, WS, ONND, OIDN), after make demo -> reports/compare
#   pareto     the accuracy-vs-time Pareto front -> reports/pareto
#   paper      ablations, compare and pareto in order, their work against the budget -> reports/paper; then make readme
#   release    the model release (issue 62): renders, teacher, 3 students, val, bench, ship -> denoiser/models, reports/release
#              (hours: resumable, run it again after an interruption; docs/release.md)
ARGS ?=
demo ablations compare pareto: setup
	$(VENV)/bin/denoiser-pipeline pipeline=$@ $(ARGS)
release: setup blender-venv
	$(VENV)/bin/denoiser-pipeline pipeline=release $(ARGS)
paper: setup
	$(VENV)/bin/denoiser-pipeline pipeline=paper $(ARGS) && $(MAKE) readme

# Copy every results block of the reports into docs/results.md (never typed by hand): make demo's
# table (and its Blender table), the ablations, the comparison, the Pareto front, make paper's budget,
# the recipe check (denoiser-pipeline pipeline=recipe_check) and make gpu-check's block; make demo's
# table also into README.md, its one results table. A report
# not made yet is said and skipped. SUMMARY: another summary. copy SUMMARY MARKER FILE [IMAGE].
SUMMARY ?= reports/demo/summary.md
RESULTS ?= docs/results.md
readme:
	@copy() { if [ -f "$$1" ]; then python3 scripts/readme_results.py --summary "$$1" --readme "$$3" --marker "$$2" $${4:+--image "$$4"}; \
		else echo "$$1: not made yet, its block ($$2) in $$3 left as it is"; fi; }; \
	copy $(SUMMARY) results README.md; \
	copy $(SUMMARY) results $(RESULTS); \
	if [ -f $(SUMMARY) ] && grep -q '<!-- blender:begin -->' $(SUMMARY); then copy $(SUMMARY) blender $(RESULTS); fi; \
	copy reports/ablations/summary.md ablations $(RESULTS) reports/ablations/crops_a1.png:docs/images/ablations_a1.png; \
	copy reports/compare/summary.md compare $(RESULTS); \
	copy reports/pareto/pareto.md pareto $(RESULTS) reports/pareto/accuracy_vs_time.png:docs/images/pareto.png; \
	copy reports/paper/summary.md paper $(RESULTS); \
	copy reports/recipe_check/summary.md recipe_check $(RESULTS); \
	if [ -f reports/recipe_check/summary.md ] && grep -q '<!-- recipe_cycles:begin -->' reports/recipe_check/summary.md; then \
		copy reports/recipe_check/summary.md recipe_cycles $(RESULTS); fi; \
	copy docs/results/gpu.md gpu $(RESULTS)

# Fail (one line per block) when what a results block measures changed since its commit (a pure move
# does not count): rerun, then copy (make readme).
readme-check: setup
	$(PY) scripts/readme_check.py

lint: setup
	$(VENV)/bin/ruff check denoiser tests hydra_plugins train.py

# The device check of a lent GPU (docs/gpu.md): GPU tests, 1080p inference, training steps, a short
# GPU training run and the CPU evaluation of its checkpoint -> docs/results/gpu.md. No setup: the
# lent machine has its own torch; scripts/gpu_carry.sh prepares what it lacks (.gpu_carry/).
gpu-check:
	bash scripts/gpu_check.sh

# Generalisation to a real renderer: small Blender Cycles test sequences (scripts/blender_sequences.py,
# rendered with the `bpy` wheel in its own venv, never in $(VENV)) into data/blender/test/ (six
# fast-object-motion sequences fast_301..306: fresh seeds, issue 49), the val split (fast_101..103, other
# seeds: `make blender-val` alone, BLENDER_VAL_ARGS) into data/blender/val/, then
# denoiser-eval on them (noisy input, OIDN, and the checkpoints of BLENDER_CKPT) into reports/blender/,
# and the ceiling a demodulating network meets on their noisy albedo (python -m denoiser.commands.tools.albedo_bound).
# Once they exist, `make demo` also evaluates its teacher and students on them (reports/demo/blender/,
# a table in reports/demo/summary.md).
#   make blender BLENDER_CKPT='{student: reports/demo/runs/.../last.ckpt}'
#   make blender BLENDER_EVAL_ARGS='max_frames=4 ~baselines.oidn_balanced'   (more eval overrides)
# Sequences already rendered with the same settings are skipped. Needs Python 3.11 for bpy 5.0.
BLENDER_VENV   ?= .venv-blender
BLENDER_PYTHON ?= $(shell command -v python3.11 || echo python3)
BLENDER_DATA   ?= data/blender
BLENDER_ARGS   ?= --size 128 --frames 8 --spp 4 --ref-spp 1024
BLENDER_VAL_ARGS ?= --size 128 --frames 8 --spp 4 --ref-spp 512
BLENDER_CKPT   ?=
BLENDER_EVAL_ARGS ?=
BLENDER_OUT    ?= reports/blender
BLENDER_PURPOSE ?= make blender: report

$(BLENDER_VENV)/.installed:
	test -x $(BLENDER_VENV)/bin/python || $(BLENDER_PYTHON) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/python -m pip install -q "bpy>=4.2" numpy
	touch $@

# the bpy venv alone (denoiser-render-blender runs in it)
blender-venv: $(BLENDER_VENV)/.installed

# Debian's aarch64 cross compiler and QEMU, so that the extension's SIMD layer is also checked on NEON
# (tests/inference/test_ovext_simd.py; issue 66): needs root and apt-get (about 20 s), fails otherwise
neon-tools:
	@if command -v aarch64-linux-gnu-g++ >/dev/null && command -v qemu-aarch64 >/dev/null; then exit 0; fi; \
	if [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; then \
		echo "neon-tools: needs root and apt-get (apt-get install g++-aarch64-linux-gnu qemu-user)"; exit 1; fi; \
	apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
		g++-aarch64-linux-gnu qemu-user >/dev/null

blender-val: $(BLENDER_VENV)/.installed
	$(BLENDER_VENV)/bin/python scripts/blender_sequences.py --root $(BLENDER_DATA) --split val $(BLENDER_VAL_ARGS)

blender: setup $(BLENDER_VENV)/.installed blender-val
	$(BLENDER_VENV)/bin/python scripts/blender_sequences.py --root $(BLENDER_DATA) --split test $(BLENDER_ARGS)
	$(VENV)/bin/denoiser-eval layout=blender data.root=$(BLENDER_DATA) split=test out_dir=$(BLENDER_OUT) \
		'purpose=$(BLENDER_PURPOSE)' $(if $(BLENDER_CKPT),'ckpt=$(BLENDER_CKPT)') $(BLENDER_EVAL_ARGS)
	$(VENV)/bin/python -m denoiser.commands.tools.albedo_bound $(BLENDER_DATA)/test --out $(BLENDER_OUT)/albedo_bound.md
