"""Bench-only harnesses for the peer tools (SEP, cedar-solve, tetra3rs, astrometry.net).

See README.md in this folder.  Nothing in the startrack package imports these.
"""
