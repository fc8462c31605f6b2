"""startrack: a star tracker pipeline, from night-sky pictures to spacecraft attitude.

The package is split by pipeline stage (``catalog``, ``camera``, ``rotations``,
``render``, ``centroid``, ``kvector``, ``labels``, ``identify``, ``attitude``,
``track``).  Importing :mod:`startrack` is deliberately light: numba, OpenCV,
astropy and h5py are imported only inside the functions that need them, so that
``startrack --help`` answers at once.
"""
from startrack._version import __version__

__all__ = ["__version__"]
