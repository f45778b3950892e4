# The two commands of the README. Each installs what it needs first (tools/setup.sh).
PYTHON ?= python3
export PYTHON

.PHONY: setup demo test test-all
setup:
	@bash tools/setup.sh

demo: setup
	$(PYTHON) -m usdfiber render examples/demo.usda -o build/demo.exr

test: setup
	$(PYTHON) -m pytest -q

# Includes the long physics runs (marked slow).
test-all: setup
	$(PYTHON) -m pytest -q -m ""
