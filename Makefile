# Roost — the two commands a newcomer needs are `make demo` and `make test`.
# Everything else is a step of those two, runnable on its own.
SHELL := /bin/bash
.DEFAULT_GOAL := help

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
PY := $(BIN)/python
STAMP := $(VENV)/.installed
CLUSTER_DIR := .cluster
export PATH := $(CURDIR)/$(BIN):$(PATH)

.PHONY: help
help: ## list the targets
	@grep -hE '^[a-zA-Z0-9_-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-16s %s\n", $$1, $$2}'

# setup.py and the C extension too: the editable install builds the extension in place
# (agent/roost_agent/_udpbatch.c), so an edit to it is built again before the next run
$(STAMP): pyproject.toml setup.py agent/roost_agent/_udpbatch.c
	@echo "setup: creating $(VENV) with Roost and its dev tools (pip's log: $(VENV)/pip.log)"
	@$(PYTHON) -m venv $(VENV)
	@docker/debian-packages.sh cc=gcc >/dev/null 2>&1 || true  # without it: reported below
	@{ $(PY) -m pip install --upgrade pip && $(PY) -m pip install -e '.[dev]'; } > $(VENV)/pip.log 2>&1 \
	  || { tail -n 40 $(VENV)/pip.log; echo "setup: pip failed; the whole log is $(VENV)/pip.log"; exit 1; }
	@$(PY) -c 'import roost_agent._udpbatch' 2>/dev/null \
	  || echo "setup: the C extension was not built (why: $(VENV)/pip.log); the agent reads and routes in Python"
	$(PY) -m roost_localcluster.clients install
	touch $@

.PHONY: setup
setup: $(STAMP) ## create .venv with Roost, dev tools, kubectl and helm

.PHONY: crds
crds: $(STAMP) ## regenerate crds/ (and the chart's copies) from the models in api/
	$(PY) -m roost_api.crd crds
	$(MAKE) --no-print-directory chart-crds

.PHONY: chart-crds
chart-crds: ## copy crds/ into charts/roost/crds (Helm installs CRDs from there)
	cp crds/roost.dev_*.yaml charts/roost/crds/

.PHONY: lint
lint: $(STAMP) ## ruff
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

.PHONY: typecheck
typecheck: $(STAMP) ## mypy --strict on every Roost package
	$(BIN)/mypy

.PHONY: cluster-build
cluster-build: ## build (or reuse) the control-plane binaries (and kine) cached under ~/.cache/roost
	localcluster/build-control-plane.sh
	localcluster/build-control-plane.sh kine >/dev/null

.PHONY: node-build
node-build: ## build (or reuse) a real node's programs: kubelet, kube-proxy, containerd, CNI plugins, pause image
	localcluster/build-node.sh >/dev/null

.PHONY: images
images: ## build the operator and agent images for amd64 and arm64 (buildah; arm64 under qemu) into ~/.cache/roost/images
	docker/build-images.sh

.PHONY: cluster-up
cluster-up: $(STAMP) cluster-build ## start the control plane in the background; prints the kubeconfig
	$(BIN)/roost-cluster up --dir $(CLUSTER_DIR)

.PHONY: cluster-down
cluster-down: $(STAMP) ## stop the control plane started by cluster-up
	$(BIN)/roost-cluster down --dir $(CLUSTER_DIR)

# The test tiers (docs/contributing.md): `make check` is the loop while editing (lint,
# types, unit tests: no sockets, threads, sleeps or programs; under a minute of CPU);
# `make integration` and `make e2e` need the control-plane build; `make test` runs them
# all, plus the control-plane suites again on kine, as CI does.
REPORTS := .test-reports
PYTEST_REPORT = $(BIN)/pytest --junitxml=$(REPORTS)/$(1).xml
# Most integration files wait (on sockets, timers, the control plane), so pytest-xdist
# workers take whole files each, two side by side, each worker with its own control
# plane, the longest files first (LONGEST_FIRST in tests/conftest.py: xdist's own order,
# by test count, left the longest files to the end); tests marked `serial` (they judge
# real time, or need the whole machine) run after, alone. `WORKERS=1` runs the first pass
# in one worker.
WORKERS ?= 2
PARALLEL := -n $(WORKERS) --dist loadfile --no-loadscope-reorder -m 'not serial'
# the serial pass of $(2) (pytest's 5, "no tests collected", when none of them is serial)
PYTEST_SERIAL = $(call PYTEST_REPORT,$(1)) -m serial $(2) || [ $$? -eq 5 ]

.PHONY: check
check: $(STAMP) lint typecheck ## lint, types and the unit tests: what to run before every commit
	@mkdir -p $(REPORTS)
	$(call PYTEST_REPORT,unit) tests/unit

.PHONY: unit
unit: $(STAMP) ## the unit tests only (pure: no cluster, sockets, threads or sleeps)
	$(BIN)/pytest tests/unit

.PHONY: integration
integration: $(STAMP) cluster-build ## real parts together: UDP MAVLink, processes, the control plane; and the sync-paths example
	@$(MAKE) --no-print-directory integration-parallel integration-serial

# integration's two passes: the files in $(WORKERS) workers, then what must run alone and
# the sync-paths example. The tests tests/integration/test_compiled_agent.py runs against
# the compiled build (the agent's message path, as the images ship it) run there only.
LEAVE := --leave-to-compiled
.PHONY: integration-parallel integration-serial
integration-parallel: $(STAMP) cluster-build
	@mkdir -p $(REPORTS)
	$(call PYTEST_REPORT,integration) $(PARALLEL) $(LEAVE) tests/integration
integration-serial: $(STAMP) cluster-build
	@mkdir -p $(REPORTS)
	$(call PYTEST_SERIAL,integration-serial,$(LEAVE) tests/integration)
	$(call PYTEST_REPORT,sync-paths) examples/missions/sync-paths

# The e2e files wait on pods, kubelets, timers and flights, not on the CPU: two workers
# take whole files each, each worker with its own control plane and real-node pool (the
# node network's subnets, namespaces and cgroups are per pool; tests/conftest.py
# puts the longest file first). The flights judged in real time (`serial`) run after, two
# files at a time: a flight costs a fraction of a core, and what starved them was the
# first pass's images under qemu, image builds and the browser tests beside them.
E2E_PARALLEL := -n $(WORKERS) --dist loadfile --no-loadscope-reorder -m 'not arm64_node and not serial'
E2E_SERIAL := -n $(WORKERS) --dist loadfile

.PHONY: e2e
e2e: $(STAMP) cluster-build ## end to end: the sandbox, the chart, the images, the dashboard in a browser, real nodes (skip without)
	@docker/build-images.sh >/dev/null || echo "images: not built (above: why); tests/e2e/test_image_run.py skips or fails with the reason"
	@docker/build-images.sh --mission examples/missions/sync-paths >/dev/null || echo "sync-paths image: not built (above: why); tests/e2e_node/test_sync_paths_real.py fails with the reason"
	@$(MAKE) --no-print-directory browser || echo "browser: not installed (above: why); the dashboard's browser tests skip"
	@mkdir -p $(REPORTS)
	$(call PYTEST_REPORT,e2e) $(E2E_PARALLEL) tests/e2e tests/e2e_node
	$(call PYTEST_SERIAL,e2e-serial,$(E2E_SERIAL) tests/e2e tests/e2e_node)

# `make test` starts the image builds first, in the background at the lowest CPU
# priority: most of the integration tier waits on sockets, timers and the control plane,
# so a build (minutes when Roost's sources changed) runs in the idle time, and the e2e
# tier's own call finds it done or waits for it (the image cache's lock).
.PHONY: images-background
images-background: $(STAMP)
	@mkdir -p $(REPORTS)
	@echo "images: building in the background at low priority (log: $(REPORTS)/images.log)"
	@{ nice -n 19 docker/build-images.sh && nice -n 19 docker/build-images.sh --mission examples/missions/sync-paths; } >$(REPORTS)/images.log 2>&1 </dev/null &

.PHONY: test
test: ## the whole suite: check, integration, e2e, the control-plane suites on kine, KinD; then the 25 slowest tests
	@rm -rf $(REPORTS)
	@$(MAKE) --no-print-directory images-background
	@$(MAKE) --no-print-directory check
	@$(MAKE) --no-print-directory -j2 integration-parallel kine-beside
	@$(MAKE) --no-print-directory integration-serial e2e
	$(call PYTEST_SERIAL,kine-serial,--datastore kine $(KINE_SUITES))
	ROOST_KIND_JUNIT=$(CURDIR)/$(REPORTS)/kind.xml tests/e2e/kind/run.sh
	@$(PY) -m tests.support.durations $(REPORTS)/*.xml

# The control-plane and operator suites again on kine+SQLite, the datastore K3s runs on;
# `make test-kine` runs every control-plane test on it. In `make test` they run in one
# worker beside the integration tier's first pass, which leaves most of the CPU idle
# (its tests wait on sockets, timers and the control plane); the output goes to a log,
# so the integration pass's progress stays readable, and its summary line follows.
KINE_SUITES := tests/integration/test_control_plane.py tests/integration/test_vehicle_operator.py \
  tests/integration/test_mission_operator.py

.PHONY: kine-beside
kine-beside: $(STAMP) cluster-build
	@mkdir -p $(REPORTS)
	@echo "kine: the control-plane suites on kine+SQLite, beside the integration pass (log: $(REPORTS)/kine.log)"
	@$(call PYTEST_REPORT,kine) --datastore kine -m 'not serial' $(KINE_SUITES) >$(REPORTS)/kine.log 2>&1 \
	  || { tail -n 80 $(REPORTS)/kine.log; echo "kine: failed (above: the end of its log)"; exit 1; }
	@echo "kine: $$(tail -n 1 $(REPORTS)/kine.log)"

.PHONY: test-kine
test-kine: $(STAMP) cluster-build ## every control-plane test on kine+SQLite (K3s's datastore) instead of etcd
	$(BIN)/pytest --datastore kine -m cluster tests

.PHONY: browser
browser: ## install Debian's chromium and chromium-driver (the dashboard's browser tests and bench)
	docker/debian-packages.sh chromium=chromium chromedriver=chromium-driver

.PHONY: bench
bench: $(STAMP) cluster-build ## run the benchmarks; writes bench/results.json
	$(PY) -m bench

.PHONY: run-operator
run-operator: $(STAMP) ## run the operator in the foreground against $$KUBECONFIG (default .cluster/kubeconfig)
	KUBECONFIG=$${KUBECONFIG:-$(CURDIR)/$(CLUSTER_DIR)/kubeconfig} $(BIN)/roost-operator

.PHONY: demo
demo: $(STAMP) ## start the local fleet sandbox (builds the control plane with a progress bar; Ctrl-C stops it)
	$(BIN)/roost sandbox up

.PHONY: e2e-node
e2e-node: $(STAMP) cluster-build node-build ## the chart's real pods on real harness nodes (kubelet+containerd; needs root)
	@docker/build-images.sh >/dev/null || echo "images: not built (above: why); the chart's real-node tests skip or fail with the reason"
	@docker/build-images.sh --mission examples/missions/sync-paths >/dev/null || echo "sync-paths image: not built (above: why); tests/e2e_node/test_sync_paths_real.py fails with the reason"
	$(BIN)/pytest -m 'not arm64_node' tests/e2e_node

.PHONY: e2e-arm64
e2e-arm64: $(STAMP) cluster-build node-build ## the chart's agent on an arm64 node under qemu (needs root, binfmt_misc)
	@docker/build-images.sh >/dev/null || echo "images: not built (above: why); the arm64 node test skips or fails with the reason"
	localcluster/build-node.sh --arch arm64 >/dev/null
	$(BIN)/pytest -m arm64_node tests/e2e_node

.PHONY: sandbox-full
sandbox-full: $(STAMP) cluster-build ## the largest sandbox (25 vehicles) end to end; both cores for ~1.5 min
	$(BIN)/pytest tests/integration/test_sandbox_full_fleet.py

.PHONY: e2e-kind
e2e-kind: $(STAMP) ## end-to-end suite on a 4-node KinD cluster (docker, or podman as root; skips otherwise)
	tests/e2e/kind/run.sh

.PHONY: clean
clean: ## remove the virtualenv and local state (keeps the ~/.cache build)
	rm -rf $(VENV) $(CLUSTER_DIR) .sandbox .mypy_cache .ruff_cache .pytest_cache $(REPORTS)
