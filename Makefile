# startrack: `make demo` and `make test` are all a fresh machine needs.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
ST     := $(VENV)/bin/startrack
OUT    ?= demo-output

.PHONY: install demo test test-fast bench clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	@touch $@

demo: install
	@mkdir -p $(OUT)
	@echo "== 1. The shipped catalog, filtered as paper 000 does (Hp 2.5 to 6.59, epoch 2026.9)"
	$(ST) catalog-filter --mag-min 2.5 --mag-max 6.59 --epoch 2026.9 -o $(OUT)/catalog-p000.h5
	@echo
	@echo "== 2. How many stars does paper 000's sensor see? (8 x 8 deg, Hp <= 6.59)"
	$(ST) catalog-stats --fov-deg 8 --size 480x480 --mag-max 6.59 --samples 100000 --seed 1
	@echo
	@echo "== 3. And paper 003's? (20 x 20 deg, Hp <= 5.0)"
	$(ST) catalog-stats --fov-deg 20 --size 1024x1024 --mag-max 5.0 --samples 100000 --seed 1
	@echo
	@echo "Outputs are in $(OUT)/."

test: install
	$(PY) -m pytest -q

bench: install
	$(PY) benchmarks/run.py

clean:
	rm -rf $(OUT) .pytest_cache .hypothesis
