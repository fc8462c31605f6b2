#!/usr/bin/env bash
# Reproduce the papers' identification comparisons with startrack evaluate.
#   examples/reproduce-papers.sh [COUNT] [SWEEP_COUNT] [TABLE2_COUNT]
# Defaults are the papers' sizes where affordable: 10,000 attitudes for paper 003 Table 3
# and for the sweeps, 100,000 for paper 004 Table 2.  Results: examples/results/*.txt|json|png
set -euo pipefail
cd "$(dirname "$0")/.."
ST=${ST:-.venv/bin/startrack}
PY=${PY:-.venv/bin/python}
N=${1:-10000}
NS=${2:-10000}
NT=${3:-100000}
W=${WORK:-examples/results/work}
R=examples/results
mkdir -p "$W" "$R"
ALL=pyramid,voting,brightness,labelling,grid

# Paper 003: 20 x 20 deg, 1024 x 1024, catalog to magnitude 5.0, 5" (3 sigma), 0.2 mag, 10 brightest.
$ST build-kvector --fov-deg 20 --size 1024x1024 --mag-max 5.0 -o "$W/p003-kvector.h5" -q
$ST build-labels --fov-deg 20 --mag-max 5.0 -o "$W/p003-labels.h5" -q
# brightness needs Eq. 9's calibration (In_k of a magnitude-k star), measured the paper's way: the brightest
# identified star of 100 other frames of the sensor, averaged (examples/intensity_calibration.py).
CAL3=$($PY examples/intensity_calibration.py -d "$W/p003-kvector.h5" --fov-deg 20 --size 1024x1024 --mag-max 5.0 \
       --sigma-arcsec 1.667 --mag-noise 0.2 --frames 100 --seed 1003)
echo "paper 003 sensor: --brightness-calibration $CAL3"
P003=(-d "$W/p003-kvector.h5" -d "$W/p003-labels.h5" --fov-deg 20 --size 1024x1024 --mag-max 5.0
      --sigma-arcsec 1.667 --mag-noise 0.2 --max-stars 10 --seed 3 -j 2 -q -a "$ALL" --brightness-calibration "$CAL3")
$ST evaluate "${P003[@]}" --count "$N" --false-stars 0 --min-stars 3 --json -o "$R/p003-table3-no-false.json" \
    > "$R/p003-table3-no-false.txt"
$ST evaluate "${P003[@]}" --count "$N" --false-stars 1 --min-stars 4 --json -o "$R/p003-table3-false-4.json" \
    > "$R/p003-table3-false-4.txt"
$ST evaluate "${P003[@]}" --count "$N" --false-stars 1 --min-stars 5 --json -o "$R/p003-table3-false-5.json" \
    > "$R/p003-table3-false-5.txt"

# Paper 004: 24 x 24 deg, 1200 x 1200, magnitude 5.2, 38" (1 sigma).
$ST build-kvector --fov-deg 24 --size 1200x1200 --mag-max 5.2 -o "$W/p004-kvector.h5" -q
$ST build-labels --fov-deg 24 --mag-max 5.2 -o "$W/p004-labels.h5" -q
CAL4=$($PY examples/intensity_calibration.py -d "$W/p004-kvector.h5" --fov-deg 24 --size 1200x1200 --mag-max 5.2 \
       --sigma-arcsec 38 --frames 100 --seed 1004)
echo "paper 004 sensor: --brightness-calibration $CAL4"
P004=(-d "$W/p004-kvector.h5" -d "$W/p004-labels.h5" --fov-deg 24 --size 1200x1200 --mag-max 5.2
      --sigma-arcsec 38 --seed 4 -j 2 -q)
$ST evaluate "${P004[@]}" -a labelling,pyramid,grid --count "$NT" --json -o "$R/p004-table2.json" > "$R/p004-table2.txt"
# Table 2 taken apart: each identification's time split into the search and the shared verification.
$PY examples/p004_time_split.py --frames "$NT" --kvector "$W/p004-kvector.h5" --labels "$W/p004-labels.h5" \
    -o "$R/p004-time-split.json"
$ST evaluate "${P004[@]}" -a "$ALL" --brightness-calibration "$CAL4" --count "$NS" --focal-error-pct 0,0.25,0.5,1,2 \
    --json -o "$R/p004-fig7-focal.json" --plot examples/robustness-focal-error.png > "$R/p004-fig7-focal.txt"
$ST evaluate "${P004[@]}" -a "$ALL" --brightness-calibration "$CAL4" --count "$NS" --false-stars 0,1,2,3,4,5 \
    --json -o "$R/p004-fig9-false-stars.json" --plot examples/compare-false-stars.png > "$R/p004-fig9-false-stars.txt"
# Paper 003's claim itself: the scope of the brightness-referenced search and its time beside the pyramid.
$PY examples/p003_scope.py --frames "$NS" --database "$W/p003-kvector.h5" -o "$R/p003-scope.json"
echo "results in $R"
