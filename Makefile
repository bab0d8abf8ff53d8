# dcrad: the two fresh-machine commands are `make demo` and `make test`.
PY    ?= python3
VENV  ?= .venv
BIN   := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test bench clean proto

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

## install, then solve the built-in office floor; writes out/office/
demo: install
	$(BIN)/dcrad solve office --out out/office

## install, then run the whole test suite
test: install
	$(BIN)/python -m pytest -q

## print benchmark figures (never run by CI)
bench: install
	$(BIN)/python bench/bench_solver.py

clean:
	rm -rf out build dist *.egg-info test-artifacts

## regenerate the gRPC/protobuf code from proto/ (committed; a test checks it is fresh)
proto: install
	$(BIN)/python -m grpc_tools.protoc -I proto --python_out=. --grpc_python_out=. --pyi_out=. proto/dcrad/v1/dcrad.proto
