# Every target sets itself up on a fresh machine: .venv, the CPU torch wheel, the project.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup run test bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# The default experiment (ch3_floor), then its figures and report.
run: $(STAMP)
	@dir=outputs/ch3_floor/$$(date +%Y-%m-%d_%H-%M-%S); \
	$(PY) train.py hydra.run.dir=$$dir && $(PY) analyze.py $$dir && \
	echo "  figures:     $$dir/analysis/ (claims: $$dir/analysis/report.md)"

test: $(STAMP)
	$(PY) -m pytest -n 2 -q

bench: $(STAMP)
	$(PY) benchmarks/bench_floor.py
	$(PY) benchmarks/bench_preprocessor.py

clean:
	rm -rf $(VENV) outputs/*/ .pytest_cache
