# Two commands on a fresh machine: `make demo` (agent on simulated drives) and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test venv bench clean sysdeps opcua-client

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

venv: $(STAMP) opcua-client

## opcua-client: node-opcua-client (pinned in tests/system/opcuabed.py) into .venv/opcua-client, never git;
## the independent OPC UA client of tests/system/test_opcua.py (needs node and npm: deploy/apt-packages.txt)
opcua-client: $(STAMP)
	$(PY) -m tests.system.opcuabed

## sysdeps: Debian packages the tests need (deploy/apt-packages.txt; installs them when root)
sysdeps:
	bash deploy/system-deps.sh

## demo: run a bus agent on 4 simulated drives; in another shell: .venv/bin/drivectl status
demo: $(STAMP)
	$(VENV)/bin/bus-agent --sim 4

## test: the whole suite (root tests create their own veth pairs and namespaces)
test: $(STAMP) sysdeps opcua-client
	$(PY) -m pytest -q $(PYTEST_ARGS)

bench: $(STAMP)
	$(PY) -m bench.run_all

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
