# startrack: `make demo` and `make test` are all a fresh machine needs.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
ST     := $(VENV)/bin/startrack
OUT    ?= demo-output

.PHONY: install demo test lint bench bench-blind bench-peers reproduce clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,plot,cluster]'
	$(ST) cache build
	@touch $@

demo: install
	@mkdir -p $(OUT)
	@echo "== 1. The shipped catalog, filtered as paper 000 does (Hp 2.5 to 6.59, epoch 2026.9)"
	$(ST) catalog-filter --mag-min 2.5 --mag-max 6.59 --epoch 2026.9 -o $(OUT)/catalog-p000.h5
	@echo
	@echo "== 2. How many stars does paper 003's sensor see? (20 x 20 deg, Hp <= 5.0)"
	$(ST) catalog-stats --fov-deg 20 --size 1024x1024 --mag-max 5.0 --count 100000 --seed 1
	@echo
	@echo "== 3. A real night-sky photo (ESA/Gustav Pettersson, CC BY-SA 3.0 IGO), solved with no other input"
	$(ST) solve examples/data/sky.tiff --plot $(OUT)/sky-solved.png --wcs $(OUT)/sky.wcs.fits > $(OUT)/sky.json
	@$(PY) -c "import json; d = json.load(open('$(OUT)/sky.json')); a = d['attitude']; s = d['solve']; \
	print(f\"   RA {a['ra']:.4f} deg, Dec {a['dec']:+.4f} deg, roll {a['roll']:.3f} deg; field {s['fov_deg'][0]:.3f} x \
	{s['fov_deg'][1]:.3f} deg; {a['n_stars']} stars; 1-sigma {a['sigma_cross_boresight_arcsec']:.1f}\\\" \
	cross-boresight, {a['sigma_roll_arcsec']:.0f}\\\" roll\")"
	@echo "   picture: $(OUT)/sky-solved.png   WCS: $(OUT)/sky.wcs.fits"
	@echo
	@echo "== 4. Render Orion, then centroid | identify | attitude, and compare with the truth"
	$(ST) build-kvector --fov-deg 20 --size 1024x1024 --mag-max 5.5 -o $(OUT)/db20.h5
	$(ST) render --fov-deg 20 --size 1024x1024 --ra 83.8 --dec -1.2 --roll 30 --seed 1 -o $(OUT)/orion.png \
	  --preview $(OUT)/orion-preview.png -q \
	  | $(ST) centroid -q | $(ST) identify -d $(OUT)/db20.h5 -q | $(ST) attitude -q > $(OUT)/orion.json
	@$(PY) -c "import json; from startrack.rotations import attitude_error, quaternion_to_dcm as A; \
	d = json.load(open('$(OUT)/orion.json')); t, c, r = attitude_error(A(d['attitude']['quaternion']), A(d['truth']['quaternion'])); \
	print(f\"   truth RA 83.8 Dec -1.2 roll 30 -> solved RA {d['attitude']['ra']:.4f} Dec {d['attitude']['dec']:+.4f} \
	roll {d['attitude']['roll']:.3f}; error {c*3600:.2f}\\\" cross-boresight, {r*3600:.1f}\\\" roll\")"
	@echo "   pictures: $(OUT)/orion-preview.png (8-bit, stretched; orion.png keeps the sensor's 16 bits for the pipeline)"
	@echo
	@echo "Outputs are in $(OUT)/.  Next: startrack --help"

test: install
	$(PY) -m pytest -q -n 2

lint: install
	$(VENV)/bin/ruff check startrack tests benchmarks

bench-peers: install
	$(PY) -m pip install --quiet -e '.[bench]'
	bash benchmarks/peers/setup_peers.sh

# make bench [SECTIONS="identify track"]: benchmarks/run.py's sections (`benchmarks/run.py --list` names them)
bench: bench-peers
	$(PY) benchmarks/run.py $(SECTIONS)

bench-blind: bench-peers
	$(PY) benchmarks/blind_bench.py

reproduce: install
	bash examples/reproduce-papers.sh
	bash examples/tracking.sh
	bash examples/paper001_single_star.sh
	$(PY) examples/paper000.py
	bash examples/paper000_pipeline.sh 300
	$(PY) examples/p003_fig1.py
	$(PY) examples/paper_reports.py

clean:
	rm -rf $(OUT) .pytest_cache .hypothesis bench-output
