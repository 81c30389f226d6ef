# Two commands for a fresh clone:  make demo  |  make test
# Both create .venv when it is missing and install the package into it.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.scmr-installed
AOT    := $(VENV)/.scmr-aot

.PHONY: demo test bench clean help pyc postgresql

help:
	@echo "make demo   run the fleet demo (cloud, leader, 4 robots, a cloud outage, a report)"
	@echo "make test   run the whole test suite (installs Debian's postgresql package if initdb is missing)"
	@echo "make bench  run the benchmarks (writes bench-*.json)"

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@echo "installing scmr-mesh and its pinned dependencies into $(VENV) ..."
	@$(PY) -m pip install -q --disable-pip-version-check --upgrade pip > $(VENV)/install.log 2>&1 \
	  && $(PY) -m pip install --disable-pip-version-check -e '.[test,bench]' >> $(VENV)/install.log 2>&1 \
	  || { tail -40 $(VENV)/install.log; echo "install failed: full log in $(VENV)/install.log"; exit 1; }
	@touch $(STAMP)

# the pipeline kernels compiled ahead of time (a peer starts without numba);
# a failed build only costs start-up time: the numba JIT takes over
$(AOT): $(STAMP) scmr_mesh/imaging/_srm_kernels.py scmr_mesh/imaging/_aot.py
	@$(PY) -m scmr_mesh.imaging._aot || true
	@touch $(AOT)

# bytecode of the package, written even under PYTHONDONTWRITEBYTECODE=1 (else
# every peer compiles its modules at each start: about 35 ms of CPU)
pyc: $(STAMP)
	@$(PY) -m compileall -q scmr_mesh > /dev/null

demo: $(STAMP) $(AOT) pyc
	$(VENV)/bin/scmr demo

# Debian's PostgreSQL server programs (initdb, postgres): the tests and `scmr up --clouds N`
# start a server of their own in a folder of the run; nothing runs as a system service.
postgresql:
	@if ! command -v initdb >/dev/null 2>&1 && ! ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then \
	  if [ "$$(id -u)" != 0 ]; then echo "PostgreSQL missing: run 'sudo apt-get install -y postgresql' (the tests start a server of their own)"; exit 1; fi; \
	  echo "installing Debian's postgresql package (initdb is missing) ..."; \
	  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql; } > /tmp/scmr-apt-postgresql.log 2>&1 \
	    || { tail -20 /tmp/scmr-apt-postgresql.log; echo "apt-get install postgresql failed (log: /tmp/scmr-apt-postgresql.log)"; exit 1; }; \
	fi

test: $(STAMP) $(AOT) pyc postgresql
	$(PY) -m pytest -q

bench: $(STAMP) $(AOT) pyc
	$(VENV)/bin/scmr bench pipeline --json bench-pipeline.json
	$(VENV)/bin/scmr bench mesh --json bench-mesh.json

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache runs
