#!/usr/bin/env bash
# The Unix way: one real photo through the three stages, each a separate process.
#   examples/pipeline.sh [OUTDIR]
set -euo pipefail
cd "$(dirname "$0")"
ST=${ST:-$(cd .. && pwd)/.venv/bin/startrack}
OUT=${1:-out}
mkdir -p "$OUT"
# A database for this lens (11.4 x 8.6 deg), stars to Hp 6.5.
[ -f "$OUT/esa-db.h5" ] || $ST build-kvector --camera data/camera.json --mag-max 6.5 -o "$OUT/esa-db.h5" -q
$ST centroid data/sky.tiff --camera data/camera.json \
  | $ST identify --database "$OUT/esa-db.h5" \
  | $ST attitude --wcs "$OUT/sky.wcs.fits" \
  > "$OUT/sky.json"
$ST plot "$OUT/sky.json" --kind image -o "$OUT/sky-solved.png" -q
python3 -c "import json; a = json.load(open('$OUT/sky.json'))['attitude']; \
print(f\"RA {a['ra']:.4f}  Dec {a['dec']:+.4f}  roll {a['roll']:.3f} deg  ({a['n_stars']} stars, \
{a['sigma_cross_boresight_arcsec']:.1f}\\\" cross-boresight, {a['sigma_roll_arcsec']:.0f}\\\" roll, 1 sigma)\")"
