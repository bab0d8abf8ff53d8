# dcrad: the two fresh-machine commands are `make demo` and `make test`.
PY    ?= python3
VENV  ?= .venv
BIN   := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test test-fast lint bench clean proto

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

## install, then solve the built-in office floor on two local workers (a shared run); writes out/office/
demo: install
	$(BIN)/dcrad solve office --workers 2 --out out/office

## install, then run the whole test suite (needs Docker and Chromium: see docs/guide.md, Tests)
test: install
	$(BIN)/python -m pytest -q

## the suite without the tests that need a Docker Engine or Chromium (markers docker, browser)
test-fast: install
	$(BIN)/python -m pytest -q -m "not docker and not browser"

## ruff and mypy, as CI runs them before the tests (settings in pyproject.toml)
lint: install
	$(BIN)/ruff check .
	$(BIN)/mypy

## print benchmark figures with short settings (never run by CI); every bench/bench_*.py is listed here
BENCH := \
	"bench_solver.py" \
	"bench_divide.py --sizes 2x3 --ks 1,2,4 --targets 0.2" \
	"bench_service.py" \
	"bench_binning.py --short" \
	"bench_stiff.py --rhos 0.99 --patch 0.2 --time-limit 10" \
	"bench_scale.py --rooms 3,8 --max-rays 2000000 --no-outputs" \
	"bench_scaling.py --rows 6 --cols 6 --ks 1,2,4,8" \
	"bench_checkpoint.py --rows 4 --cols 4" \
	"bench_accuracy.py --scenes cornell --accuracies 0.1,0.05" \
	"bench_real_scenes.py 50000" \
	"bench_upload.py --mb 50" \
	"bench_open_floor.py --cells 20 --ks 2,8 --seeds 1 --rays-per-power 2e5" \
	"bench_share.py --scenes office:rows=3,cols=3 --accuracy 0.05" \
	"bench_direct.py --scenes office" \
	"bench_corpus.py --models office2" \
	"bench_bias.py cornell" \
	"bench_stop.py office --accuracy 0.02" \
	"bench_setup.py --scene office:rows=4,cols=4 --patch-size 0.25 --reps 1" \
	"bench_luminaires.py --accuracy 0.05 --no-reference" \
	"bench_sigterm.py office:rows=3,cols=3 --workers 0 --delays 3" \
	"bench_code.py" \
	"bench_daylight.py --reference-accuracy 0.01 --radiance-high '-ab 5 -ad 2048 -as 1024 -aa 0.1 -ar 256'" \
	"bench_coordinator_memory.py -- $(BIN)/dcrad solve office --workers 2 --accuracy 0.1 --out out/bench-coordinator-memory"
bench: install
	@for f in bench/bench_*.py; do case ' $(BENCH) ' in *'"'$$(basename $$f)* ) ;; \
	  *) echo "make bench: $$f is not in BENCH (Makefile)"; exit 1;; esac; done
	@for b in $(BENCH); do echo "== bench/$$b"; t=$$(date +%s); $(BIN)/python bench/$$b || exit 1; \
	  echo "== $$(( $$(date +%s) - t )) s"; done

clean:
	rm -rf out build dist *.egg-info test-artifacts

## regenerate the gRPC/protobuf code from proto/ (committed; a test checks it is fresh)
proto: install
	$(BIN)/python -m grpc_tools.protoc -I proto --python_out=. --grpc_python_out=. --pyi_out=. proto/dcrad/v1/dcrad.proto
