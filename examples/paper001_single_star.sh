#!/usr/bin/env bash
# Paper 001's single-star mode (Case 2) in a tracking sequence.
#   examples/paper001_single_star.sh [FRAMES_PER_PHASE] [OUTDIR]
#
# Paper 001 (Masood-Ur-Rehman et al.): in tracking mode, when only one star is found in the
# prediction windows, the attitude comes from that star alone plus "empirical" stars (the other
# predicted stars shifted by the observed offset), solved with weighted QUEST.  Here a 12 x 9 deg,
# 1024 x 768 camera tracks the field of Sirius (0.1, 0.05 deg/s) for three phases of
# FRAMES_PER_PHASE frames each: 100 ms exposures, then 0.2 ms exposures (as an exposure control
# would cut them in stray light: only Sirius, Hp -1.1, stays above the detection limit), then 100 ms
# again.  `startrack track` is lost in space on the first frame, tracks, runs the single-star mode on
# the frames where one star is found, and tracks again.  Every frame's mode and error against the
# render's truth is printed; results: OUTDIR/track-single-star.json (per-frame rows, modes, RMS by
# mode, from `startrack plot --kind track`) and OUTDIR/track-single-star.png.
set -euo pipefail
cd "$(dirname "$0")/.."
ST=${ST:-.venv/bin/startrack}
PY=${PY:-.venv/bin/python}
N=${1:-10}
OUT=${2:-examples/results}
W=${WORK:-$OUT/work}/p001-single-star
mkdir -p "$W" "$OUT"
[ -f "$W/db.h5" ] || $ST build-kvector --fov-deg 12 --size 1024x768 --mag-max 6.0 -o "$W/db.h5" -q
SEQ=(--fov-deg 12 --size 1024x768 --ra 101.3 --dec -16.7 --roll 10 --frames $((3 * N)) --rate-deg-s 0.1,0.05,0.0
     --frame-interval-s 0.1 --time 2026-11-21T22:00:00Z --mag-max 7 --seed 1)
# The same sequence (same attitudes, times, noise seed) at both exposures; the track takes its phases from each.
rm -rf "$W/long" "$W/short"
$ST render "${SEQ[@]}" --exposure-ms 100 -o "$W/long/frame.png" -q > "$W/long.jsonl"
$ST render "${SEQ[@]}" --exposure-ms 0.2 -o "$W/short/frame.png" -q > "$W/short.jsonl"
{ sed -n "1,${N}p" "$W/long.jsonl"; sed -n "$((N + 1)),$((2 * N))p" "$W/short.jsonl"
  sed -n "$((2 * N + 1)),$((3 * N))p" "$W/long.jsonl"; } > "$W/sequence.jsonl"
$ST track "$W/sequence.jsonl" -d "$W/db.h5" -q > "$W/track.jsonl" || [ $? -eq 1 ]
$ST plot "$W/track.jsonl" --kind track --title "paper 001: one star in frames $N-$((2 * N - 1))" \
    -o "$OUT/track-single-star.png" --json -q > "$W/summary.json"
$PY - "$W/track.jsonl" "$W/summary.json" "$OUT/track-single-star.json" "$N" <<'EOF'
import json
import sys

from startrack.rotations import attitude_error, quaternion_to_dcm

track_path, summary_path, out_path, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
doc = json.load(open(summary_path))
rows = []
print("frame  exposure_ms  predicted  found  mode           cross-boresight(\")  roll(\")")
for i, line in enumerate(open(track_path)):
    d = json.loads(line)
    t, a = d.get("track") or {}, d.get("attitude") or {}
    cross = roll = None
    if a.get("status") == "ok":
        _, c, r = attitude_error(quaternion_to_dcm(a["quaternion"]), quaternion_to_dcm(d["truth"]["quaternion"]))
        cross, roll = round(float(c) * 3600, 2), round(float(r) * 3600, 2)
    rows.append({"frame": i, "exposure_ms": d["image"]["exposure_ms"], "predicted": t.get("predicted"),
                 "found": t.get("found"), "mode": t.get("mode"), "empirical_stars": t.get("empirical_stars"),
                 "cross_arcsec": cross, "roll_arcsec": roll})
    print(f"{i:5d}  {d['image']['exposure_ms']:11g}  {t.get('predicted') or '-':>9}  {t.get('found') or '-':>5}  "
          f"{t.get('mode') or '-':13s}  {cross if cross is not None else '-':>18}  {roll if roll is not None else '-':>7}")
one = [r["frame"] for r in rows if r["found"] == 1]
single = [r["frame"] for r in rows if r["mode"] == "single-star"]
doc.update(command=f"examples/paper001_single_star.sh {n}", frames_per_phase=n, rows=rows,
           one_star_frames=one, single_star_frames=single)
json.dump(doc, open(out_path, "w"), indent=1)
print(f"single-star mode on {len(single)} frames; {len(one)} frames had one star found in the windows")
EOF
