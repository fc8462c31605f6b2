#!/usr/bin/env bash
# Tracking mode on rendered sequences (12 deg FOV, 1024 x 768):
#  1. 200 frames at 0.5 deg/s, 10 black frames injected (frames 100-109);
#  2. a 3 deg/s slew with smear (20 ms exposures: 5 px trails), the rate from the streaks.
# track exits 1 when some frame has no attitude (the black frames): accepted here.
# Results: examples/track-*.png (per-frame errors), examples/results/track-*.json (mode fractions, RMS, recovery).
set -euo pipefail
cd "$(dirname "$0")/.."
ST=${ST:-.venv/bin/startrack}
N=${1:-200}
W=${WORK:-examples/results/work}
R=examples/results
mkdir -p "$W" "$R"
$ST build-kvector --fov-deg 12 --size 1024x768 --mag-max 6.0 -o "$W/track-db.h5" -q
$ST render --fov-deg 12 --size 1024x768 --ra 120 --dec 30 --roll 15 --frames "$N" --rate-deg-s 0.3,0.4,0.0 \
    --frame-interval-s 0.1 --time 2026-11-21T22:00:00Z --mag-max 7 --blackout $((N / 2)):10 --seed 21 \
    -o "$W/slow/frame.png" -q > "$W/slow.jsonl"
$ST track "$W/slow.jsonl" -d "$W/track-db.h5" -q > "$W/slow-track.jsonl" || [ $? -eq 1 ]
$ST plot "$W/slow-track.jsonl" --kind track --title "0.5 deg/s, 10 black frames" -o examples/track-0.5deg-s.png \
    --json -q > "$R/track-0.5deg-s.json"
$ST render --fov-deg 12 --size 1024x768 --ra 250 --dec -20 --roll -40 --frames "$N" --rate-deg-s 0.0,3.0,0.0 \
    --frame-interval-s 0.1 --time 2026-11-21T22:00:00Z --mag-max 7 --exposure-ms 20 --seed 22 \
    -o "$W/slew/frame.png" -q > "$W/slew.jsonl"
$ST track "$W/slew.jsonl" -d "$W/track-db.h5" -q > "$W/slew-track.jsonl" || [ $? -eq 1 ]
$ST plot "$W/slew-track.jsonl" --kind track --title "3 deg/s slew, 5 px smear" -o examples/track-3deg-s-slew.png \
    --json -q > "$R/track-3deg-s-slew.json"
echo "results in $R and examples/track-*.png"
