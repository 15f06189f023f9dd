# Every target creates .venv and installs the project when missing.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
OUT     ?= demo_out

.PHONY: demo test bench lint install clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# torch / torchvision first: these exact releases lie on this machine's disk.
	$(BIN)/pip install -q torch==2.14.1 torchvision==0.29.1
	$(BIN)/pip install -q -e '.[dev,ray,peer]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/sgde demo --out $(OUT)

# one worker per core (at most 4), a test file's tests together so each module-scoped fixture is built once
test: lint
	$(BIN)/python -m pytest -n auto --maxprocesses 4 --dist loadfile tests

bench: $(STAMP)
	$(BIN)/sgde bench --fast --json bench.json

# ruff; import-linter on a copy of the package laid out as installed (adapters/ and export/ inside sgde_plugin/),
# so the layer contract in .importlinter sees every module; radon's complexity limits (tools/complexity.py).
lint: $(STAMP)
	$(BIN)/ruff check sgde_plugin adapters export tests tools
	rm -rf .lint && mkdir -p .lint && cp -r sgde_plugin .lint/ && cp -r adapters export .lint/sgde_plugin/
	cd .lint && PYTHONPATH=. ../$(BIN)/lint-imports --no-cache ../.importlinter
	$(BIN)/python tools/complexity.py

clean:
	rm -rf $(VENV) build *.egg-info demo_out bench.json .lint
