# The two commands of the README: `make run` (set up, then the main job) and `make test`.
SHELL := /bin/bash
VENV ?= .venv
RUN_DIR ?= runs/default
PYTEST_ARGS ?=

.PHONY: setup setup-calvin setup-simpler run test lint bench clean

setup:
	@bash scripts/setup.sh

# the CALVIN env server's Python 3.11 venv (.venv-calvin): only for configs with env.suite calvin
setup-calvin:
	@bash scripts/setup_calvin.sh

# the SIMPLER env server's Python 3.11 venv (.venv-simpler) and, without a GPU, Vulkan on the CPU
# (.vulkan-cpu: lavapipe + our layer): only for configs with env.suite simpler
setup-simpler:
	@bash scripts/setup_simpler.sh

run: setup
	$(VENV)/bin/idr-eval run conf/default.yaml --out $(RUN_DIR)

test: setup
	$(VENV)/bin/ruff check pipeline workers training tests benchmarks lerobot_policy_idr
	$(VENV)/bin/ruff format --check pipeline workers training tests benchmarks lerobot_policy_idr
	$(VENV)/bin/python -m pytest $(PYTEST_ARGS)

lint: setup
	$(VENV)/bin/ruff check --fix pipeline workers training tests benchmarks lerobot_policy_idr
	$(VENV)/bin/ruff format pipeline workers training tests benchmarks lerobot_policy_idr

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
	rm -rf runs .pytest_cache
