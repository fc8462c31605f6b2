"""numba kernels, grouped by stage.  Only numpy and :mod:`._jit` here (never numba itself: see there).

Every kernel is ``@njit(cache=True)`` so that a command-line call, a fresh
process each time, loads compiled code from ``__pycache__`` instead of
recompiling.  Public wrappers elsewhere validate input and fix dtypes and
memory layout; kernels see only contiguous arrays and scalars.
"""
