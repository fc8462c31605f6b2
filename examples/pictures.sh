#!/usr/bin/env bash
# One picture of each kind startrack draws, made by the commands themselves: this is how the
# pictures committed in examples/ are made (the README's sky-solved.png among them).
#   examples/pictures.sh            rewrites examples/*.png (about 2 minutes on 2 cores)
#   examples/pictures.sh OUTDIR     writes them to OUTDIR instead
set -euo pipefail
cd "$(dirname "$0")"
ST=${ST:-$(cd .. && pwd)/.venv/bin/startrack}
OUT=${1:-.}
mkdir -p "$OUT"
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT

# image: the README's picture, an ESA photo solved blind (no camera, no field of view given)
$ST solve data/sky.tiff --plot "$OUT/sky-solved.png" -q > "$WORK/solved.json"
# residuals: the solved attitude's residual per star (the camera as solve fitted it)
$ST plot "$WORK/solved.json" --kind residuals -o "$OUT/picture-residuals.png" -q
# centroid: what was detected and what was set aside
$ST centroid data/sky.tiff --camera data/camera.json --plot "$OUT/picture-centroid.png" -q > "$WORK/stars.json"
# identify: the same photo with a k-vector database built for its lens
$ST build-kvector --camera data/camera.json --mag-max 6.5 -o "$WORK/esa.h5" -q
$ST identify -d "$WORK/esa.h5" --plot "$OUT/picture-identify.png" -q < "$WORK/stars.json" > /dev/null
# track: a rendered sequence turning at 0.4 deg/s, with five black frames (exit status 1: they have no attitude)
$ST build-kvector --fov-deg 12 --size 1024x768 --mag-max 6.5 -o "$WORK/db12.h5" -q
$ST render --fov-deg 12 --size 1024x768 --frames 40 --rate-deg-s 0.3,-0.2,0.2 --frame-interval-s 0.1 \
    --blackout 20:5 --seed 1 -o "$WORK/seq/frame.png" -q > "$WORK/seq.jsonl"
$ST track -d "$WORK/db12.h5" -q < "$WORK/seq.jsonl" > "$WORK/track.jsonl" || [ $? -eq 1 ]
$ST plot "$WORK/track.jsonl" --kind track --title "tracking at 0.4 deg/s, frames 20-24 black" \
    -o "$OUT/picture-track.png" -q
# evaluate: success rate and time of three algorithms against false stars (paper 003's sensor)
$ST build-kvector --fov-deg 20 --size 1024x1024 --mag-max 5.0 -o "$WORK/p003.h5" -q
$ST evaluate -d "$WORK/p003.h5" -a pyramid,voting,brightness --fov-deg 20 --size 1024x1024 --mag-max 5 \
    --sigma-arcsec 1.667 --false-stars 0,1,2,3 --count 200 --seed 1 -j 2 --plot "$OUT/picture-evaluate.png" -q \
    > /dev/null
# constellations: a rendered 40 x 30 deg field of Orion, solved blind and drawn with the stick figures and names
$ST render --fov-deg 40 --size 1200x900 --ra 84 --dec 3 --roll 10 --seed 3 --mag-max 6.5 -o "$WORK/wide.png" -q \
    > /dev/null
$ST solve "$WORK/wide.png" --no-aberration -o "$WORK/wide.json" -q
$ST plot "$WORK/wide.json" --constellations --mag-max 4.5 -o "$OUT/picture-constellations.png" -q
# the demo's Orion frame (make demo): the 16-bit image for the pipeline, and the 8-bit stretched preview people see
$ST render --fov-deg 20 --size 1024x1024 --ra 83.8 --dec -1.2 --roll 30 --seed 1 -o "$WORK/orion.png" \
    --preview "$OUT/orion.png" -q > /dev/null
# the papers' charts drawn again from the results reproduce-papers.sh wrote (Wilson 95 % bars, an honest axis)
$ST plot results/p004-fig9-false-stars.json --kind evaluate -o "$OUT/compare-false-stars.png" -q
$ST plot results/p004-fig7-focal.json --kind evaluate -o "$OUT/robustness-focal-error.png" -q
ls -l "$OUT"/sky-solved.png "$OUT"/picture-*.png "$OUT"/orion.png "$OUT"/compare-false-stars.png \
    "$OUT"/robustness-focal-error.png
