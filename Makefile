# sparsetools: `make demo` and `make test` do all set-up on a fresh machine.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
STAMP := $(VENV)/.setup-done
TORCH_VERSION ?= 2.13.0

.PHONY: setup demo test lint bench clean sample-data docs-pictures acceptance wheel

setup: $(STAMP)

$(STAMP): pyproject.toml
	@if [ "$$(id -u)" = "0" ] && ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then \
		echo ">> installing libusb-1.0-0 (needed by Open3D, the open3d extra: ICP)"; \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0) \
			|| echo ">> warning: could not install libusb-1.0-0; ICP (accumulate --icp) will be unavailable"; \
	fi
	test -x $(PY) || python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	# torch first, pinned, so that no CUDA build is pulled in by the extras below
	$(PIP) install -q torch==$(TORCH_VERSION)
	$(PIP) install -q -e ".[train,dask,dev,viz,open3d,yaml]"
	touch $(STAMP)

demo: setup
	$(VENV)/bin/sparsetools demo --out out/demo
	@echo "report: out/demo/report.md"

test: setup
	$(PY) -m pytest -q

lint: setup
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/ruff format --check src tests benchmarks

# The wheel users install, in dist/. build/ is removed first: setuptools reuses it and would
# pack files deleted from src/ since its last build (split lists once shipped as .txt).
wheel: setup
	rm -rf build
	$(PIP) wheel -q --no-deps -w dist .

bench: setup
	$(PY) benchmarks/run_all.py

# The papers' claims on the bundled training, every model with two seeds (about 1.5 hours on
# 2 cores; resumable): benchmarks/results/acceptance_claims.json (docs/selfsup.md#acceptance).
acceptance: setup
	$(PY) benchmarks/acceptance_claims.py --out out/acceptance_claims

sample-data: setup
	$(VENV)/bin/sparsetools synth-scene -o sample_data/synthetic --seed 0 --frames 3 --overwrite
	rm -rf sample_data/synthetic/.sparsetools  # the run's record is not part of the sample data

# Every picture of docs/img/ from its script (a few minutes; needs ../shared/data/real). The
# training and self-supervised pictures take hours: benchmarks/acceptance_train.py and
# acceptance_selfsup.py (see docs/train.md, docs/selfsup.md), not run here.
docs-pictures: setup
	for s in docs/img/make_*.py; do $(PY) $$s || exit 1; done
	$(PY) benchmarks/acceptance_accumulate.py --docs
	$(PY) docs/img/make_plots.py
	rm -rf docs/img/.sparsetools  # the records of viz -o docs/img/...: not part of the docs

clean:
	rm -rf out .pytest_cache build dist
