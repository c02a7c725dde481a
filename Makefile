# teachpath: `make run` and `make test` do all the set-up themselves (see scripts/setup.sh).
VENV := .venv
BIN := $(VENV)/bin
OUT ?= demo_out

.PHONY: setup run demo test bench lint clean

setup:
	@scripts/setup.sh

# The main job. For now: the bundled demo reconstruction (synthetic cylinder-edge scene),
# which writes its accuracy table, the reconstructed path and a plot to $(OUT)/.
run: setup
	$(BIN)/teachpath demo --out-dir $(OUT)

test: setup
	$(BIN)/python -m pytest -q -p no:cacheprovider tests --ignore=tests/bench

# Speed and accuracy tables; never part of `make test` (timings on a shared machine are noisy).
bench: setup
	@command -v wrk >/dev/null || scripts/setup.sh --bench-tools
	$(BIN)/python -m pytest -q -s -p no:cacheprovider tests/bench

lint: setup
	$(BIN)/ruff check recon drivers service tests

clean:
	rm -rf $(VENV) $(OUT) *.egg-info
