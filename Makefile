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
	$(BIN)/pip install -q -e '.[dev,ray]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/sgde demo --out $(OUT)

test: $(STAMP)
	$(BIN)/ruff check sgde_plugin adapters export tests
	$(BIN)/python -m pytest tests

bench: $(STAMP)
	$(BIN)/sgde bench --fast --json bench.json

lint: $(STAMP)
	$(BIN)/ruff check sgde_plugin adapters export tests

clean:
	rm -rf $(VENV) build *.egg-info demo_out bench.json
