"""The ``startrack`` command line: one click group, one module per command.

Each command is a thin shell: parse options, make one library call, write the
result.  Heavy imports (numba, OpenCV, astropy, h5py) happen inside command
bodies so that ``startrack --help`` is instant.
"""
import os as _os

# The commands' linear algebra is small (3 x 3 to a few hundred unknowns): OpenBLAS's worker threads never pay
# there, and while they wait they spin, taking a CPU from find_stars' threads and from -j's workers (`solve` of
# 64 images: 0.2 CPU-s of 0.75 spent spinning, the wall time the same).  One thread, unless the caller says
# otherwise; set before numpy is first imported (no command module imports it before this).
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
