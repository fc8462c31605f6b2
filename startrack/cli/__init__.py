"""The ``startrack`` command line: one click group, one module per command.

Each command is a thin shell: parse options, make one library call, write the
result.  Heavy imports (numba, OpenCV, astropy, h5py) happen inside command
bodies so that ``startrack --help`` is instant.
"""
