# Setup is folded into the targets: `make demo` and `make test` each install what they need.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# the demo writes inside the clone (ignored by git); make demo DEMO=/some/folder puts it elsewhere
DEMO   ?= demo-output
# bash: the demo quotes the paths it prints with printf %q
SHELL  := /bin/bash

.PHONY: install demo test bench clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# nvidia-ncore depends on torch; the conversion never imports it, so take the CPU build
	# (a local wheel on these machines, the PyTorch CPU index elsewhere) instead of the CUDA one.
	$(PY) -m pip install -q "torch==2.13.0" || \
	  $(PY) -m pip install -q torch --index-url https://download.pytorch.org/whl/cpu
	# constraints.txt: the versions CI is known to work with (s3fs/aiobotocore and boto3 pin botocore
	# differently, and an unconstrained resolve backtracks for many minutes)
	$(PY) -m pip install -q -e ".[test]" -c constraints.txt
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	rm -rf "$(DEMO)"
	$(VENV)/bin/ncore-convert synth argoverse2 --out "$(DEMO)/source" --seconds 2 --seed 0
	$(VENV)/bin/ncore-convert --root-dir "$(DEMO)/source" --output-dir "$(DEMO)/out" argoverse2-v4 --split val
	@# the next command, with absolute paths quoted for the shell (a clone's path may hold a space)
	@cli="$$(cd "$(VENV)/bin" && pwd)/ncore-convert"; out="$$(cd "$(DEMO)" && pwd)"; \
	  sequence="$$(ls "$$out"/out/*/*.json | head -n 1)"; \
	  echo; echo "Converted into $$out/out. Next, draw what was written (lidar on the cameras, a bird's-eye view):"; \
	  printf '  %q preview %q --out %q\n' "$$cli" "$$sequence" "$$out/preview"; \
	  echo "(source .venv/bin/activate puts ncore-convert on your PATH; docs/cli.md lists every command)"

test: $(STAMP)
	# lint and formatting first: both are part of the tests (pyproject.toml [tool.ruff])
	$(VENV)/bin/ruff check src tests bench
	$(VENV)/bin/ruff format --check src tests bench
	# one worker per core; a file's tests stay on one worker (module fixtures built once), the cases
	# of OWN_SCOPE tests go out one by one, slowest files first (tests/conftest.py); the JUnit report
	# gives the time per file: python bench/suite_table.py build/test-report.xml
	# the package's bytecode, written once: where PYTHONDONTWRITEBYTECODE is set (as on CI), every
	# process the tests start (CLI runs, fork servers, Ray workers) would compile it again
	$(PY) -m compileall -q src
	$(PY) -m pytest -q -n auto --dist loadfile --no-loadscope-reorder --junitxml=build/test-report.xml

bench: $(STAMP)
	$(PY) bench/bench_argoverse2.py
	$(PY) bench/bench_runner.py
	$(PY) bench/bench_tbv.py
	$(PY) bench/bench_opencood.py
	$(PY) bench/bench_noise.py
	$(PY) bench/bench_validate.py
	$(PY) bench/bench_input_checks.py
	$(PY) bench/bench_consumers.py
	$(PY) bench/bench_speed.py
	$(PY) bench/bench_floor.py
	$(PY) bench/bench_shared_runs.py

clean:
	rm -rf $(VENV) build src/*.egg-info
