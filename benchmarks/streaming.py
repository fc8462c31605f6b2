"""Streaming and memory of the frame pipes (issue 13), feeds tests/cli/test_streaming.py (hold_pipeline).

hold
    Writes frame 0 into ``startrack identify -d DB | startrack attitude`` and
    reads its result (start-up), then frame 1, holds the pipe open for
    ``--hold-s`` seconds before frame 2, and prints the time from writing frame 1
    to reading its attitude (it must come out while frame 2 is still held back).
memory
    Peak resident memory (``/usr/bin/time -v``-equivalent: ``ru_maxrss`` of each
    stage) of ``render --count N --stars-only | identify | attitude`` for several N.

Usage::

    python benchmarks/streaming.py hold --database db20.h5 --hold-s 20
    python benchmarks/streaming.py memory --database db20.h5 --counts 1000,10000
"""
from __future__ import annotations

import argparse
import json
import os
import selectors
import subprocess
import sys
import time

RENDER = ["render", "--stars-only", "--fov-deg", "20", "--size", "1024x1024", "--mag-limit", "5",
          "--sigma-px", "0.2", "--max-stars", "12", "-q"]


def _startrack(*args):
    return [sys.executable, "-m", "startrack", *map(str, args)]


def read_line(stream, timeout_s: float) -> bytes | None:
    """One line from a pipe, or ``None`` after ``timeout_s`` seconds."""
    sel = selectors.DefaultSelector()
    sel.register(stream, selectors.EVENT_READ)
    buf = b""
    end = time.monotonic() + timeout_s
    while not buf.endswith(b"\n"):
        left = end - time.monotonic()
        if left <= 0 or not sel.select(left):
            return None
        chunk = os.read(stream.fileno(), 1)
        if not chunk:
            return buf or None
        buf += chunk
    return buf


def hold_pipeline(database: str, frames: list[str], hold_s: float, timeout_s: float = 300.0):
    """Run the held-open pipe.

    ``frames[:-2]`` (if any) are written first and their results read (start-up:
    imports, database, compiled kernels).  Then ``frames[-2]`` is written and
    its result read while ``frames[-1]`` is held back until ``hold_s`` seconds
    after ``frames[-2]`` was written; then ``frames[-1]`` is written.

    Returns (seconds from writing frames[-2] to its result, seconds from writing
    frames[-1] to its result while stdin stays open, frames[-2]'s doc,
    frames[-1]'s doc, exit codes, seconds of start-up).
    """
    ident = subprocess.Popen(_startrack("identify", "-d", database, "-q"), stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE)
    att = subprocess.Popen(_startrack("attitude", "-q"), stdin=ident.stdout, stdout=subprocess.PIPE)
    ident.stdout.close()
    try:
        t_start = time.monotonic()
        for warm in frames[:-2]:
            ident.stdin.write(warm.encode() + b"\n")
            ident.stdin.flush()
            read_line(att.stdout, timeout_s)
        startup = time.monotonic() - t_start
        t0 = time.monotonic()
        ident.stdin.write(frames[-2].encode() + b"\n")
        ident.stdin.flush()
        first = read_line(att.stdout, timeout_s)
        t_first = time.monotonic() - t0
        held = hold_s - t_first
        if held > 0:
            time.sleep(held)  # the last frame still held back: the pipe stays open
        t1 = time.monotonic()
        ident.stdin.write(frames[-1].encode() + b"\n")
        ident.stdin.flush()
        second = read_line(att.stdout, timeout_s)
        t_second = time.monotonic() - t1
        ident.stdin.close()
        codes = (ident.wait(timeout_s), att.wait(timeout_s))
    finally:
        for p in (ident, att):
            if p.poll() is None:
                p.kill()
    return (t_first, t_second, json.loads(first) if first else None, json.loads(second) if second else None, codes,
            startup)


def peak_rss_mb(count: int, database: str) -> dict:
    """Peak RSS (MB) of each stage of render | identify | attitude, frames to /dev/null."""
    code = (
        "import resource, subprocess, sys, json\n"
        f"r = subprocess.Popen({_startrack(*RENDER, '--count', count, '--seed', 1)!r}, stdout=subprocess.PIPE)\n"
        f"i = subprocess.Popen({_startrack('identify', '-d', database, '-q')!r}, stdin=r.stdout, "
        "stdout=subprocess.PIPE)\n"
        f"a = subprocess.Popen({_startrack('attitude', '-q')!r}, stdin=i.stdout, stdout=subprocess.DEVNULL)\n"
        "r.stdout.close(); i.stdout.close()\n"
        "out = {}\n"
        "for name, p in (('render', r), ('identify', i), ('attitude', a)):\n"
        "    _, status, ru = __import__('os').wait4(p.pid, 0)\n"
        "    out[name] = ru.ru_maxrss / 1024\n"
        "print(json.dumps(out))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["hold", "memory"])
    ap.add_argument("--database", "-d", required=True)
    ap.add_argument("--hold-s", type=float, default=20.0)
    ap.add_argument("--counts", default="1000,10000")
    args = ap.parse_args(argv)
    if args.what == "hold":
        frames = subprocess.run(_startrack(*RENDER, "--count", 3, "--seed", 3), capture_output=True, text=True,
                                check=True).stdout.splitlines()
        t_first, t_second, doc1, doc2, codes, startup = hold_pipeline(args.database, frames, args.hold_s)
        print(f"start-up (frame 0 in, its result out) {startup:.2f} s; frame 1 result {1000 * t_first:.0f} ms "
              f"after it was written, while frame 2 was held back {args.hold_s:g} s "
              f"(status {doc1['attitude']['status'] if doc1 else None}); frame 2 result {1000 * t_second:.0f} ms "
              f"after it was written (status {doc2['attitude']['status'] if doc2 else None}); exit codes {codes}")
    else:
        for n in (int(v) for v in args.counts.split(",")):
            t = time.monotonic()
            rss = peak_rss_mb(n, args.database)
            print(f"--count {n}: peak RSS MB " + ", ".join(f"{k} {v:.0f}" for k, v in rss.items())
                  + f" ({time.monotonic() - t:.0f} s)")


if __name__ == "__main__":
    main()
