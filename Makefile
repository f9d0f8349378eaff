# Set-up and main jobs. `make test` and `make demo` create .venv if missing and install
# everything they need (torch==2.13.0 first when no torch is present, so pip never pulls a
# multi-GB CUDA build), then run.
VENV    ?= .venv
PY      := $(VENV)/bin/python
EXTRAS  ?= render,eval,export,openvino,scale,dev
PYTEST_ARGS ?=
# The suite runs in one pytest-xdist worker process: a test that kills its process (a native
# runtime's segfault) is reported as that test's failure, by name, the worker is replaced and the
# summary still prints (issue 44; tests/test_signal_stack.py::test_make_test_survives_a_crashing_test).
PYTEST_ISOLATION ?= -p xdist -n 1 --max-worker-restart=100

.PHONY: gpu-check readme-gpu setup test demo readme-results readme-pareto readme-ablations readme-compare readme-check ovext pareto compare ablations paper readme-paper fast-motion lint clean-cache blender blender-val

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
	$(PY) scripts/readme_check.py

# Build the OpenVINO extension (denoiser/inference/ovext: one C++ header per operation) ahead of
# time into its cache ($$DENOISER_CACHE/ovext, else ~/.cache/denoiser/ovext), as a package
# maintainer or an image build would; without it, the first OpenVINO use builds it. Prints the
# library's path, or one line saying why it cannot be built (exit 1).
ovext: setup
	$(PY) -m denoiser.inference.ovext

# The whole pipeline on the simulated demo dataset (render, teacher, distilled and no-KD
# students with 3 seeds each, evaluation, benchmark). Its recipe is refine (issue 33): the paper's
# recipe first (reports/demo/runs), then its teacher and students fine-tuned on the fast-moving
# families (conf/base/motion_recipe.yaml) into reports/demo_refine/, each student evaluated as its
# weights interpolated with its start (DEMO_REFINE_ALPHA, 0.75, chosen on val), the summary in
# reports/demo_refine/summary.md. Step budgets; about 85 minutes on 2 idle CPU cores from a fresh clone
# (estimated from the stage timings of its runs on a 2-core AMD EPYC: reports/demo_refine/timings.md).
# DEMO_RECIPE=demo make demo: the paper's recipe alone, reports/demo/; DEMO_RECIPE=tune: the demo
# teacher fine-tuned on the fast-moving families and students distilled from it, reports/demo_tune/;
# DEMO_RECIPE=motion: a teacher trained on them from scratch, reports/demo_motion/ (scripts/lib.sh).
demo: setup
	VENV=$(VENV) bash scripts/demo.sh

# Copy the results table of make demo's summary (DEMO_SUMMARY) into README.md (never typed by hand).
DEMO_SUMMARY ?= reports/demo_refine/summary.md
readme-results:
	python3 scripts/readme_results.py --summary $(DEMO_SUMMARY) --readme README.md
	if grep -q '<!-- blender:begin -->' $(DEMO_SUMMARY); then \
		python3 scripts/readme_results.py --summary $(DEMO_SUMMARY) --readme README.md --marker blender; \
	else echo "$(DEMO_SUMMARY): no Blender table (make blender, then make demo): README's left as it is"; fi

# Fail (one line per block) when what a README results block measures (denoiser/nn, conf/net, conf/kernel,
# conf/experiment, conf/dataset) changed since its commit (a pure move does not count): rerun, then copy.
readme-check: setup
	$(PY) scripts/readme_check.py --readme README.md

# Copy the Pareto table of reports/pareto/pareto.md and its plot (docs/images/pareto.png) into README.md.
readme-pareto:
	python3 scripts/readme_results.py --summary reports/pareto/pareto.md --marker pareto \
		--image reports/pareto/accuracy_vs_time.png:docs/images/pareto.png

# The accuracy-vs-time Pareto front of the demo student (docs/pareto.md): reuses make demo's data
# and teacher (or makes them), trains 8 distilled variants (experiment=pareto, short runs), times
# them one at a time and writes reports/pareto/. Resumable. Knobs: PARETO_* in scripts/pareto.sh.
pareto: setup
	VENV=$(VENV) bash scripts/pareto.sh

# The paper's comparison on the demo's held-out scenes (docs/baselines.md): renders data/demo_compare
# (demo's test split with per-sample radiance, for ONND), trains NPPD and WS by the demo student's
# recipe (seeds COMPARE_SEEDS, default "0 1 2"), evaluates and times them with ONND (COMPARE_ONND=0:
# off), OIDN, the teacher and the students of make demo -> reports/compare/summary.md with the
# Fig. A.2 / A.3 tables and ranking lines (conf/compare_summary.yaml). Resumable.
compare: setup
	VENV=$(VENV) bash scripts/compare.sh

# Copy the comparison's block of reports/compare/summary.md (<!-- compare:begin --> ... end) into README.md.
readme-compare:
	python3 scripts/readme_results.py --summary reports/compare/summary.md --marker compare

# The paper's Fig. A.1 (the pyramid against no_pyramid and direct) and its distillation ablations
# (no_kd, no_unlabeled, no_adversarial, no_param_transfer, kernels k3 and k7) on the demo's held-out
# scenes: reuses make demo's data, teacher and students (none = its distilled students, no_kd = its
# students on references alone; run make demo first), trains the other variants with 3 seeds each
# (same steps and teacher), evaluates and times them -> reports/ablations/summary.md (paired intervals
# against the full recipe, one sentence per claim of the paper). Resumable. Knobs: ABLATION_* in
# scripts/ablations.sh.
ablations: setup
	VENV=$(VENV) bash scripts/ablations.sh

# Copy the ablations' block of reports/ablations/summary.md and its crop figure (docs/images/ablations_a1.png)
# into README.md.
readme-ablations:
	python3 scripts/readme_results.py --summary reports/ablations/summary.md --marker ablations \
		--image reports/ablations/crops_a1.png:docs/images/ablations_a1.png

# Every figure of the paper after make demo, in order: make ablations, make compare, make pareto
# (scripts/paper.sh; each stage resumable, its wall time in reports/paper/timings.md), then the
# README copies. Its work against the budget: reports/paper/summary.md (README, "Every figure: make paper").
paper: setup
	VENV=$(VENV) bash scripts/paper.sh
	$(MAKE) readme-ablations readme-compare readme-pareto readme-paper

# Copy make paper's budget block (reports/paper/summary.md: every stage's work against the budget) into README.md.
readme-paper:
	python3 scripts/readme_results.py --summary reports/paper/summary.md --marker paper

# Issue 33's val study (moving objects), after make demo: renders the fast-motion families into
# data/fast (dataset=fast), trains teacher candidates on data/demo + data/fast (FAST_TEACHERS, 3 seeds
# each), evaluates them on the Mitsuba and Blender val splits and writes reports/fast/teachers/val_table.md;
# FAST_STUDENT_TEACHER=<candidate> also distils students from it -> reports/fast/students/val_table.md.
# Val only, never a test split. Resumable. Knobs: FAST_* in scripts/fast_motion.sh.
fast-motion: setup
	VENV=$(VENV) bash scripts/fast_motion.sh

lint: setup
	$(VENV)/bin/ruff check denoiser tests hydra_plugins train.py

# The device check of a lent GPU (docs/gpu.md): GPU tests, 1080p inference, training steps, a short
# GPU training run and the CPU evaluation of its checkpoint -> docs/results/gpu.md. No setup: the
# lent machine has its own torch; scripts/gpu_carry.sh prepares what it lacks (.gpu_carry/).
gpu-check:
	bash scripts/gpu_check.sh

# Copy the README block of docs/results/gpu.md (make gpu-check's report: the card, inference, training) into README.md.
readme-gpu:
	python3 scripts/readme_results.py --summary docs/results/gpu.md --marker gpu

# Generalisation to a real renderer: small Blender Cycles test sequences (scripts/blender_sequences.py,
# rendered with the `bpy` wheel in its own venv, never in $(VENV)) into data/blender/test/ (orbit,
# slide and six fast-object-motion sequences fast_201..206), the val split (fast_101..103, other
# seeds: `make blender-val` alone, BLENDER_VAL_ARGS) into data/blender/val/, then
# denoiser-eval on them (noisy input, OIDN, and the checkpoints of BLENDER_CKPT) into reports/blender/,
# and the ceiling a demodulating network meets on their noisy albedo (scripts/albedo_bound.py).
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

$(BLENDER_VENV)/.installed:
	test -x $(BLENDER_VENV)/bin/python || $(BLENDER_PYTHON) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/python -m pip install -q "bpy>=4.2" numpy
	touch $@

blender-val: $(BLENDER_VENV)/.installed
	$(BLENDER_VENV)/bin/python scripts/blender_sequences.py --root $(BLENDER_DATA) --split val $(BLENDER_VAL_ARGS)

blender: setup $(BLENDER_VENV)/.installed blender-val
	$(BLENDER_VENV)/bin/python scripts/blender_sequences.py --root $(BLENDER_DATA) --split test $(BLENDER_ARGS)
	$(VENV)/bin/denoiser-eval layout=blender data.root=$(BLENDER_DATA) out_dir=$(BLENDER_OUT) \
		$(if $(BLENDER_CKPT),'ckpt=$(BLENDER_CKPT)') $(BLENDER_EVAL_ARGS)
	$(VENV)/bin/python scripts/albedo_bound.py $(BLENDER_DATA)/test --out $(BLENDER_OUT)/albedo_bound.md
