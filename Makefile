# teachpath: `make run` and `make test` do all the set-up themselves (see scripts/setup.sh).
VENV := .venv
BIN := $(VENV)/bin
OUT ?= demo_out

.PHONY: setup run demo test test-fast bench lint docs clean

setup:
	@scripts/setup.sh

# The main job: the service on 127.0.0.1 with the embedded defaults (SQLite in ./teachpath_data,
# the simulated arm, a demo session); it prints the URL to open, with the access token.
run: setup docs
	$(BIN)/teachpath serve --demo

# The documentation site (mkdocs-material, strict: a broken link or reference fails it) into
# site/, with the diagrams' script from npm; the service serves it at /guide.
docs: setup
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet
	mkdir -p site/js && cp service/ui/vendor/mermaid/mermaid.min.js site/js/

# The offline demo: reconstruct the synthetic cylinder scene, write table and plots to $(OUT)/.
demo: setup
	$(BIN)/teachpath demo --out-dir $(OUT)

# Then the store and API suites again, every service on a fresh database of a real PostgreSQL
# server the tests start (tests/postgres.py; the migration and two-instance tests always do).
PG_SUITES = tests/service/test_api.py tests/service/test_session_lifecycle.py \
	tests/service/test_api_inputs.py

# The numerical core's tests first, then the rest, each on both cores (one process per core, a
# test file's tests in one process). The simulated and fake arms stream in real time beside the
# other process: their tests hold to tolerances measured so (the fake controller's lost-link
# threshold and watchdog are relaxed for them, tests/drivers/fake_ur_fixture.py).
test: setup
	$(BIN)/python -m pytest -q -p no:cacheprovider -n 2 --dist loadfile tests/recon
	$(BIN)/python -m pytest -q -p no:cacheprovider -n 2 --dist loadfile --durations=25 tests \
		--ignore=tests/bench --ignore=tests/recon
	TEACHPATH_TEST_DATABASE=postgresql $(BIN)/python -m pytest -q -p no:cacheprovider $(PG_SUITES)

# The edit loop's suite (about 2 minutes): the numerical core's and the drivers' tests that take
# well under a second or two, on both cores. The slow ones (marked `slow`: a fake controller in
# real time, dense reference searches, the real parts), the service, the browser and the
# end-to-end suites run in `make test`, which CI runs.
test-fast: setup
	$(BIN)/python -m pytest -q -p no:cacheprovider -n 2 -m "not bench and not slow" tests/recon \
		tests/drivers

# Speed and accuracy tables; never part of `make test` (timings on a shared machine are noisy).
bench: setup
	@scripts/setup.sh --bench-tools
	$(BIN)/python -m pytest -q -s -p no:cacheprovider -m bench tests/bench

# What CI checks before the tests (and the pre-commit hooks, .pre-commit-config.yaml, before a
# commit): ruff's rules and its formatting, the types (mypy, [tool.mypy] in pyproject.toml), the
# Dockerfile, the compose file.
lint: setup
	$(BIN)/ruff check recon drivers service tests docs/examples
	$(BIN)/ruff format --check recon drivers service tests docs/examples
	$(BIN)/mypy
	$(BIN)/hadolint docker/Dockerfile
	$(BIN)/yamllint -c .yamllint.yaml docker/compose.yaml

clean:
	rm -rf $(VENV) $(OUT) *.egg-info site
# teachpath_data/ (sessions, token) is left alone: delete it yourself to start afresh.
