#!/usr/bin/env bash
# Install the PEER tools used only by the benchmarks (never by startrack itself).
#
#   bash benchmarks/peers/setup_peers.sh            # from the repository root
#
# Idempotent: re-running only installs what is missing.
#   * sep + tetra3rs          -> the main venv (.venv), as bench-only extras
#   * cedar-solve             -> its own venv (.venv-cedar): it pins numpy<2
#   * astrometry.net + Tycho-2 index 10-19 (Debian packages) -> only as root with apt;
#     skipped with a message otherwise.
# Environment overrides: PYTHON (python3), VENV (.venv), CEDAR_VENV (.venv-cedar),
# SKIP_APT=1 to skip the Debian packages.
set -u
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "$ROOT"
PYTHON="${PYTHON:-python3}"
VENV="${VENV:-.venv}"
CEDAR_VENV="${CEDAR_VENV:-.venv-cedar}"
status=0

say() { echo "[setup_peers] $*"; }

# --- 1. sep and tetra3rs into the main venv -----------------------------------------
if [ ! -x "$VENV/bin/python" ]; then
    say "$VENV not found: run 'make install' first (creating a bare venv now)"
    "$PYTHON" -m venv "$VENV" || { say "cannot create $VENV"; exit 1; }
fi
if "$VENV/bin/python" -c 'import sep, tetra3rs' 2>/dev/null; then
    say "sep and tetra3rs already in $VENV"
else
    say "installing sep and tetra3rs into $VENV"
    "$VENV/bin/python" -m pip install --quiet sep tetra3rs || { say "pip install sep tetra3rs FAILED"; status=1; }
fi

# --- 2. cedar-solve in its own venv ---------------------------------------------------
if [ -x "$CEDAR_VENV/bin/python" ] && "$CEDAR_VENV/bin/python" -c "import tetra3, h5py" 2>/dev/null; then
    say "cedar-solve already in $CEDAR_VENV"
else
    say "creating $CEDAR_VENV with cedar-solve"
    [ -x "$CEDAR_VENV/bin/python" ] || "$PYTHON" -m venv "$CEDAR_VENV" || { say "cannot create $CEDAR_VENV"; exit 1; }
    "$CEDAR_VENV/bin/python" -m pip install --quiet --upgrade pip
    "$CEDAR_VENV/bin/python" -m pip install --quiet cedar-solve h5py || { say "pip install cedar-solve h5py FAILED"; status=1; }
fi

# --- 3. astrometry.net (Debian) ----------------------------------------------------------
if command -v solve-field >/dev/null 2>&1 && ls /usr/share/astrometry/index-tycho2-1*.fits >/dev/null 2>&1; then
    say "astrometry.net and Tycho-2 indexes already installed"
elif [ "${SKIP_APT:-0}" = 1 ]; then
    say "SKIP_APT=1: not installing astrometry.net"
elif [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
    say "not root or no apt-get: skipping astrometry.net (install astrometry.net and"
    say "astrometry-data-tycho2-10-19 by hand to benchmark solve-field)"
else
    say "installing astrometry.net astrometry-data-tycho2-10-19 (apt)"
    if DEBIAN_FRONTEND=noninteractive apt-get update -qq \
       && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
              astrometry.net astrometry-data-tycho2-10-19; then
        say "astrometry.net installed"
    else
        say "apt-get failed: skipping astrometry.net (the astrometry peer will report 'unavailable')"
    fi
fi

mkdir -p bench-output/peers
say "done (status $status)"
exit $status
