# cellctl: `make demo` shows it working, `make test` checks everything on a fresh machine.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: test demo lint typecheck pytest deps clean bench

test: deps lint typecheck pytest

# Debian packages the tests need: ser2net (a real RFC 2217 server for the link tests).
deps: $(STAMP)
	@command -v ser2net >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ]; then \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq ser2net >/dev/null) \
	      || echo "warning: could not install ser2net; its tests will be skipped"; \
	  else echo "note: ser2net missing and not root; its tests will be skipped"; fi; }

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check src tests bench
	$(BIN)/ruff format --check src tests bench

typecheck: $(STAMP)
	$(BIN)/mypy

pytest: $(STAMP)
	$(BIN)/pytest -q

demo: $(STAMP)
	$(BIN)/cellctl demo

bench: $(STAMP)
	$(BIN)/python bench/robot_download.py
	$(BIN)/python bench/many_links.py

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache
