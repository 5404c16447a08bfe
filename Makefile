# Two commands set everything up on a fresh machine:
#   make demo   -- the main job on the embedded default scene
#   make test   -- the test suite
# Both create .venv when missing, install the system library Open3D needs, the
# local CPU torch wheel first (so no dependency can pull a CUDA build), then cadalign.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.cadalign-installed
DEMO_OUT ?= runs/demo

.PHONY: demo test lint clean-venv setup

setup: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@ldconfig -p | grep -q libusb-1.0.so.0 || { \
	  echo "installing libusb-1.0-0 (needed by Open3D)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0; }
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	@$(PY) -c "import sys, torch; sys.exit('a CUDA torch build was installed; remove .venv and re-run' if torch.version.cuda else 0)"
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cadalign demo --out $(DEMO_OUT)

test: $(STAMP)
	$(PY) -m pytest -n 2 -q

lint: $(STAMP)
	$(VENV)/bin/ruff check cadalign tests

clean-venv:
	rm -rf $(VENV)
