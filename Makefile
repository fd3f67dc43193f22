# Two entry points for a fresh clone: `make demo` and `make test` (both install first).
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.vslam-installed

.PHONY: install demo test wheel-check bench clean

$(STAMP): pyproject.toml scripts/setup.sh
	VENV=$(VENV) bash scripts/setup.sh

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/vslam demo

test: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python -m pytest -q
	$(BIN)/vslam bench --check

# the wheel as `pip install .` builds it, installed non-editable in a fresh venv, run from outside the checkout
wheel-check: $(STAMP)
	VENV=$(VENV) bash scripts/check_wheel.sh

bench: $(STAMP)
	$(BIN)/vslam bench --suite configs/bench.yaml

clean:
	rm -rf runs .pytest_cache
