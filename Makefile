# cellctl: `make demo` shows it working, `make test` checks everything on a fresh machine.
# The Python .venv is made with: the system's own (/usr/bin/python3) when it is 3.11 or newer
# and has venv, else python3 on PATH (`make clean; make PY=python3.13` chooses). A distribution
# builds its Python with profile-guided and link-time optimization into one static binary: on
# the 2-core box the suite took a sixth less CPU on Debian's 3.11 than on a default source build
# (pyenv's: a shared libpython, neither), and a `cellctl` took a fifth less to start.
PY ?= $(or $(shell for py in /usr/bin/python3 python3; do \
	  $$py -c 'import sys, ensurepip, venv; sys.exit(sys.version_info < (3, 11))' 2>/dev/null \
	  && { echo $$py; break; }; done),python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# The example machine kind from outside (tests/plugins/cellctl_saw, docs/kinds.md), installed as
# a user installs a plug-in: a plain (not editable) pip install, redone when its files change.
PLUGIN := tests/plugins/cellctl_saw
PLUGIN_STAMP := $(VENV)/.plugins

.PHONY: test demo lint typecheck pytest deps clean bench

test: deps lint typecheck pytest

# Debian packages the tests need: ser2net (a real RFC 2217 server for the link tests), tmux
# (the console is checked in a real terminal), chromium (the dashboard, through Playwright),
# mosquitto (the factory's broker; the tests start their own, never the system service) and
# systemd (its systemd-analyze verifies the unit of `cellctl service install`). TOOL:PACKAGE
# where the two names differ.
DEBS := ser2net tmux chromium mosquitto systemd-analyze:systemd
deps: $(STAMP) $(PLUGIN_STAMP)
	@missing=""; for dep in $(DEBS); do command -v $${dep%%:*} >/dev/null 2>&1 || missing="$$missing $${dep##*:}"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ]; then \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null) \
	      || echo "warning: could not install$$missing"; \
	  else echo "note:$$missing missing and not root: install them (the tests that need them fail)"; fi; \
	fi

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

$(PLUGIN_STAMP): $(STAMP) $(PLUGIN)/pyproject.toml $(wildcard $(PLUGIN)/src/*/*.py)
	$(BIN)/pip install -q --no-deps --force-reinstall $(PLUGIN)
	touch $(PLUGIN_STAMP)

lint: $(STAMP)
	$(BIN)/ruff check src tests bench
	$(BIN)/ruff format --check src tests bench
	$(BIN)/lint-imports

typecheck: $(STAMP)
	$(BIN)/mypy

# Independent tests run in parallel (each has its own ports and directories). Much of a
# test's time is emulated machine time or a process starting (waiting, not computing), yet
# the suite is CPU-bound on a 2-core box: 4 workers ran its 1769 tests in 405 s with 660 s
# of CPU, 6 workers in 425 to 480 s with 740 to 800 s (each worker collects the suite and
# starts its own Chromium, and more processes share the two cores), 3 in 430 s. What
# shortens it is CPU saved (a `cellctl` that starts with less, plans that look less often).
# Work stealing keeps the long end-to-end tests from piling up on one worker at the end.
# Compiled bytecode is used and kept even where the environment turns caching off: pytest's
# own plug-ins are loaded before tests/conftest.py could turn it on, and every worker and
# every `cellctl` process compiled again. It stays in __pycache__ beside each module (git
# ignores it): pip compiled the installed packages there, and a PYTHONPYCACHEPREFIX would
# hide that and compile them all again on a fresh clone, in every worker at once.
# The tests marked alone (real-time fidelity) run after, with the box to themselves; only the
# files that mark one are collected (collecting the whole suite for one test took 5 s).
PYTEST := env -u PYTHONDONTWRITEBYTECODE $(BIN)/pytest
pytest: $(STAMP) $(PLUGIN_STAMP)
	$(PYTEST) -q -n 4 --dist worksteal -m "not alone"
	$(PYTEST) -q -m alone $$(grep -l '^@pytest.mark.alone' tests/*.py)  # real-time fidelity, alone

# `make demo DEMO_ARGS=--dashboard` leaves the dashboard up after the batch (Ctrl-C stops).
demo: $(STAMP)
	$(BIN)/cellctl demo $(DEMO_ARGS)

bench: $(STAMP)
	cd bench && for b in robot_download many_links mill_download cell_throughput api_push factory_throughput \
	    line_noise fault_reaction dnc_dripfeed dnc_many ur_cell; do \
	  ../$(BIN)/python $$b.py || exit 1; done

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache
