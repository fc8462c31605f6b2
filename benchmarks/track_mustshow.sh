#!/usr/bin/env bash
# Feeds results/results-track-2026-12-02b.md ("render -> track"): issue 16's "Must show" by the command line:
# render -> track --database with no other option, on
#  1. the issue's 60-frame sequence (0.3, -0.2, 0.5 deg/s, 0.1 s apart),
#  2. a sparse one (4-6 catalog stars per frame: a poor field, rendered to Hp 6.0),
#  3. the issue's slew (1.5, -1.0, 0.5 deg/s, 100 ms exposures: ~15 px streaks, 40 frames);
# each with track's exit status and summary line, and plot --kind track's error statistics.
#   bash benchmarks/track_mustshow.sh [WORKDIR]
set -euo pipefail
cd "$(dirname "$0")/.."
ST=${ST:-"python -m startrack"}
PY=${PY:-python}
W=${1:-bench-output/track-mustshow}
mkdir -p "$W"
uptime
echo "+ startrack build-kvector --fov-deg 12 --size 1024x768 --mag-max 6.5 -o $W/db.h5"
$ST build-kvector --fov-deg 12 --size 1024x768 --mag-max 6.5 -o "$W/db.h5" -q

summary() {  # frames with attitude, modes, catalog stars per frame, the first frame's streak rate
    $PY - "$1" <<'EOF'
import collections, json, sys
docs = [json.loads(line) for line in open(sys.argv[1]) if line.strip()]
modes = collections.Counter(d["track"]["mode"] for d in docs)
ok = sum(1 for d in docs if d["attitude"]["status"] == "ok")
stars = collections.Counter(len(d["truth"]["stars"]) for d in docs)
print(f"  {ok} of {len(docs)} frames with an attitude; modes {dict(modes)}; catalog stars per frame "
      f"(count: frames) {dict(sorted(stars.items()))}")
t = docs[0]["track"]
if t.get("streak_rate_deg_s"):
    print(f"  first frame: {t.get('detected')} detections, {t.get('streaks')} fitted streaks, rate from its streaks "
          f"alone {t['streak_rate_deg_s']} deg/s (sigma {t.get('streak_rate_sigma_deg_s')})")
last = docs[-1]["track"]
print(f"  last frame's filtered rate {[round(v, 4) for v in last['rate_deg_s']]} deg/s "
      f"(sigma {[round(v, 4) for v in last['rate_sigma_deg_s']]})")
EOF
}

run() {  # name, render options...
    local name=$1
    shift
    echo "+ startrack render --fov-deg 12 --size 1024x768 $* -o $W/$name/frame.png > $W/$name.jsonl"
    $ST render --fov-deg 12 --size 1024x768 "$@" -o "$W/$name/frame.png" -q > "$W/$name.jsonl"
    echo "+ startrack track --database $W/db.h5 < $W/$name.jsonl > $W/$name-track.jsonl"
    local rc=0
    $ST track --database "$W/db.h5" < "$W/$name.jsonl" > "$W/$name-track.jsonl" || rc=$?
    echo "  exit status $rc"
    summary "$W/$name-track.jsonl"
    echo "+ startrack plot --kind track -o $W/$name-track.png --json < $W/$name-track.jsonl"
    $ST plot --kind track -o "$W/$name-track.png" --json -q < "$W/$name-track.jsonl"
}

run seq --frames 60 --rate-deg-s 0.3,-0.2,0.5 --frame-interval-s 0.1 --seed 1
run sparse --ra 352.6 --dec -33.3 --mag-max 6.0 --frames 60 --rate-deg-s 0.3,-0.2,0.5 --frame-interval-s 0.1 --seed 5
run slew --frames 40 --rate-deg-s 1.5,-1.0,0.5 --frame-interval-s 0.1 --seed 3
uptime
