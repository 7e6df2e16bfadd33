# The two commands of the README: `make demo` and `make test`. Both set up .venv first.
VENV := .venv
STAMP := $(VENV)/.sefa-installed

.PHONY: demo test test-fast setup gpu-check docs

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/sefa demo

# Every test, in WORKERS processes (pytest-xdist): a file's tests stay in one process, so a
# module's fixture (often a tiny training) is built once. WORKERS=1 runs them in this process.
# Three on two cores: the third runs while the others wait on the commands they start (the whole
# suite on 2 cores: 14 min 36 s with 3 workers, 16 min 27 s with 2).
WORKERS ?= 3
PYTEST := $(VENV)/bin/python -m pytest -q $(if $(filter-out 1,$(WORKERS)),-n $(WORKERS) --dist loadfile)

test: $(STAMP)
	$(PYTEST)

# While working: everything but the tests marked slow (tests/markers.py), a few minutes
test-fast: $(STAMP)
	$(PYTEST) -m "not slow"

# The documentation site in site/, warnings as errors (the reference pages are generated from the
# code first, by the hook in mkdocs.yml)
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/python -m mkdocs build --strict

# On a machine with CUDA: GPU tests (device placement, bf16, NCCL, reflow GPU vs CPU, latency) and the table
gpu-check: $(STAMP)
	bash scripts/gpu_check.sh
