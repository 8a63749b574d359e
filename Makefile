# cellctl: every task a person runs, one make target each. `make test` and `make demo` set up a
# fresh machine first (system packages, .venv, the project), so nothing else needs doing by hand.
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.cellctl-installed
OUT    ?= runs/demo

.PHONY: test-long setup test test-fast lint format demo bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml constraints.txt scripts/setup.sh
	bash scripts/setup.sh
	touch $(STAMP)

# The unit tests (no marker) and the tests that only compute (`compute`, set by tests/conftest.py)
# on both cores, then every cell test and every test that starts a real-time simulator (`realtime`,
# set by tests/conftest.py from the code, in process or as a process) alone, one at a time:
# real-time simulators must not share the cores with numerical tests. Both always run; the exit
# status is the first failure's.
UNIT   := not long and not realtime and (compute or not (slow or e2e or process))
CELLS  := not long and (realtime or (not compute and (slow or e2e or process)))

test: setup
	@$(BIN)/python -m pytest -m "$(UNIT)" -n 2 --dist loadfile; unit=$$?; \
	$(BIN)/python -m pytest -m "$(CELLS)"; cells=$$?; \
	if [ $$unit -ne 0 ]; then exit $$unit; fi; exit $$cells

test-long: setup
	$(BIN)/python -m pytest -m long

test-fast: setup
	$(BIN)/python -m pytest -m "not slow and not e2e and not process"

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: setup
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

demo: setup
	$(BIN)/cellctl demo --out $(OUT)

bench: setup
	@for b in benchmarks/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache build *.egg-info
