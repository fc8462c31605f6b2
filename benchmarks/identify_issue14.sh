#!/usr/bin/env bash
# Feeds results/results-identify-2026-12-04b.md ("Issue 14's must-show"): issue 14's Must-show in one run:
# identification beside tetra3rs and cedar-solve (15 deg sensor, 1000 frames x 4 conditions), a narrow deep field,
# paper 004 Figs. 9-10 and paper 003 Table 3 rows for
# brightness, and the databases' sizes and build times for 20/12/8/6 deg sensors.
#   benchmarks/identify_issue14.sh [COUNT] [OUT_DIR]
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
ST=${ST:-"$PY -m startrack"}
N=${1:-1000}
O=${2:-bench-output/issue14}
mkdir -p "$O"
echo "start $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg)" | tee "$O/log.txt"

# 1. The 15 deg 1280x960 sensor: six algorithms (pyramid, modified-pyramid, voting, brightness, labelling, grid),
#    tetra3rs, cedar-solve on the same star lists; modified-pyramid on build-triangles' database (Hp <= 6.0, as the
#    k-vector database identify_compare.py builds).
$ST build-triangles --fov-deg 15 --size 1280x960 --mag-max 6.0 -o "$O/tri15.h5" 2>&1 | tee -a "$O/log.txt"
$PY benchmarks/identify_compare.py --count "$N" --triangles "$O/tri15.h5" --out "$O/compare.md" > /dev/null
echo "compare done $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg)" | tee -a "$O/log.txt"

# 2. Databases: size and build time, depth chosen by build-kvector itself.
for spec in "20 1280x960" "12 1280x960" "8 1280x960" "6 1392x1040"; do
    set -- $spec
    s0=$(date +%s.%N)
    $ST build-kvector --fov-deg "$1" --size "$2" -o "$O/db$1.h5" -q
    s1=$(date +%s.%N)
    echo "db $1 deg $2: $(stat -c %s "$O/db$1.h5") bytes, $(echo "$s1 - $s0" | bc) s wall, load $(cut -d' ' -f1-3 /proc/loadavg)" \
        | tee -a "$O/log.txt"
    $PY -c "import h5py,sys; f=h5py.File(sys.argv[1]); print(dict(f.attrs))" "$O/db$1.h5" > "$O/db$1.attrs.txt" 2>&1 || true
done

# 3. A narrow deep field: 6 x 4.5 deg, 1392x1040, stars to Hp 10, 2 false stars, the database above.
$ST evaluate -d "$O/db6.h5" -a pyramid --fov-deg 6 --size 1392x1040 --mag-max 10 --sigma-px 0.3 --false-stars 2 \
    --min-catalog-stars 4 --count 100 --seed 6 -q --json -o "$O/narrow.json" > "$O/narrow.txt"
echo "narrow done $(date -u +%FT%TZ)" | tee -a "$O/log.txt"

# 4. Paper 004's sensor (24 deg, 1200x1200, Hp 5.2, 38" 1 sigma): Figs. 9-10, 1-5 false stars.
$ST build-kvector --fov-deg 24 --size 1200x1200 --mag-max 5.2 -o "$O/p004-kvector.h5" -q
$ST build-labels --fov-deg 24 --mag-max 5.2 -o "$O/p004-labels.h5" -q
$ST evaluate -d "$O/p004-kvector.h5" -d "$O/p004-labels.h5" --fov-deg 24 --size 1200x1200 --mag-max 5.2 \
    --sigma-arcsec 38 --seed 4 -q -a labelling,pyramid,brightness --false-stars 1,2,3,4,5 --count "$N" \
    --json -o "$O/p004-fig9.json" > "$O/p004-fig9.txt"
echo "p004 done $(date -u +%FT%TZ)" | tee -a "$O/log.txt"

# 5. Paper 003's Table 3 rows for brightness (20 deg, 1024x1024, Hp 5.0, 5" 3 sigma, 0.2 mag, 10 brightest).
$ST build-kvector --fov-deg 20 --size 1024x1024 --mag-max 5.0 -o "$O/p003-kvector.h5" -q
CAL3=$($PY examples/intensity_calibration.py -d "$O/p003-kvector.h5" --fov-deg 20 --size 1024x1024 --mag-max 5.0 \
       --sigma-arcsec 1.667 --mag-noise 0.2 --frames 100 --seed 1003)
P003=(-d "$O/p003-kvector.h5" --fov-deg 20 --size 1024x1024 --mag-max 5.0 --sigma-arcsec 1.667 --mag-noise 0.2
      --max-stars 10 --seed 3 -q -a brightness,pyramid --brightness-calibration "$CAL3")
$ST evaluate "${P003[@]}" --count "$N" --false-stars 0 --min-stars 3 > "$O/p003-no-false.txt"
$ST evaluate "${P003[@]}" --count "$N" --false-stars 1 --min-stars 4 > "$O/p003-false-4.txt"
$ST evaluate "${P003[@]}" --count "$N" --false-stars 1 --min-stars 5 > "$O/p003-false-5.txt"
echo "calibration $CAL3; end $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg)" | tee -a "$O/log.txt"
