# One-command entry points. Everything installs into .venv from pinned versions
# (pyproject.toml), so a clean clone needs nothing installed by hand.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup run test test-slow test-compose test-slurm soak lint clean

# torch's index, when pip's own config should not choose (README, Quick start).
TORCH_INDEX ?=

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "need $(PYTHON) on PATH"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	# torch first, alone, at pyproject's pin (the one place), from TORCH_INDEX when given.
	# Else pip's config decides: these machines' find-links hold the CPU build; PyPI itself
	# gives Linux x86-64 the multi-GB CUDA build.
	$(BIN)/pip install --quiet $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX)) \
		"$$(grep -o '"torch==[^"]*"' pyproject.toml | tr -d '"')"
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

# The local cluster with its API; configs/default.yaml goes in through the API and is
# followed to the end, in lockstep: the same rows every time, `macb train`'s (tests/test_up.py),
# and a line saying what was learned. Results: runs/default/ (metrics.csv, plot.png, checkpoint.pt);
# every point stays in runs/cluster/api.sqlite3; the dashboard is on
# http://127.0.0.1:8000/ while it runs (`macb up --data-dir runs/cluster` serves it again).
run: $(STAMP)
	$(BIN)/macb up --run configs/default.yaml --out runs/default --data-dir runs/cluster --quiet-services

# Everything but the long checks (marked `slow`): ~20 minutes on 2 shared cores, in
# TEST_WORKERS pytest-xdist workers (3 on 2 cores: a cluster test spends much of its time
# waiting on its processes, so a third worker fills what two leave idle).
# TEST_WORKERS=0: one process.
TEST_WORKERS ?= 3
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -rs -m "not slow and not soak and not slurm" \
		-n $(TEST_WORKERS) --dist worksteal

# The long checks: learning (DDPG learns sparse simple; bf16 learns like fp32; the
# cluster learns like the trainer), the fault matrix, `macb reproduce` end to end, the
# longest cluster runs: ~25 minutes on 2 shared cores in TEST_SLOW_WORKERS workers (2:
# with services forked from the fork server a check spends less of its CPU starting
# processes, so two at once now finish sooner than one at a time: 24.6 against 31.7
# minutes on an AMD EPYC Zen 3, each check's own deadline met by both).
# TEST_SLOW_WORKERS=0: one process. `.ci/run` runs them after `make test`.
TEST_SLOW_WORKERS ?= 2
test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -rs -m slow -n $(TEST_SLOW_WORKERS) --dist worksteal \
		--durations=10

# A run group at thesis settings under a random fault every 10-60 s for 20 minutes
# (MACB_SOAK_MINUTES), then every count checked (tests/test_soak.py): ~25-35 minutes.
soak: $(STAMP)
	$(BIN)/python -m pytest -q -rs -s -m soak tests/test_soak.py

# docker-compose.yml's cluster in containers (tests/test_compose.py): installs Debian's
# docker.io, docker-compose and debootstrap when missing (as root; else it skips, saying
# why), starts dockerd without bridge networking if none runs (and stops it after),
# builds the images without a registry (cached by tag: docker/offline.py), runs the
# cluster on the host network's loopback, removes its containers and volumes.
test-compose: $(STAMP)
	MACB_COMPOSE_SETUP=1 $(BIN)/python -m pytest -q -rs -s -m compose tests/test_compose.py

# `macb reproduce --local --launcher slurm` and the service cluster job (`macb up
# --launcher slurm`) on a real Slurm (tests/test_slurm.py): installs Debian's munge and
# slurm-wlm when missing (as root; else it skips, saying why), starts munged, slurmctld
# and slurmd with a one-node slurm.conf in a temp folder (ports, socket and key of their
# own: tests/slurm_node.py) and stops them after: 6-8 minutes here.
test-slurm: $(STAMP)
	MACB_SLURM_SETUP=1 $(BIN)/python -m pytest -q -rs -s -m slurm tests/test_slurm.py

# mypy checks shared/, services/, cli/ and macb/ (pyproject.toml's [tool.mypy]): zero errors.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

clean:
	rm -rf $(VENV) runs .pytest_cache .mypy_cache
