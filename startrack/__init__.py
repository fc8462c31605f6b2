"""startrack: a star tracker pipeline, from night-sky pictures to spacecraft attitude.

The public API is :class:`Solver` and the typed records it returns::

    import startrack

    result = startrack.Solver().solve("sky.tiff")
    print(result.status, result.attitude.ra, result.attitude.dec)

The package is split by pipeline stage (``catalog``, ``camera``, ``rotations``,
``render``, ``centroid``, ``kvector``, ``labels``, ``identify``, ``attitude``,
``track``).  Importing :mod:`startrack` is deliberately light: the public names
are imported on first use (PEP 562), and numba, OpenCV, astropy and h5py only
inside the functions that need them, so that ``startrack --help`` answers at once.
"""
from startrack._version import __version__

# public name -> module that defines it
_PUBLIC = {
    "Solver": "startrack.solver",
    "SolveOptions": "startrack.solve",
    "Camera": "startrack.camera",
    "Catalog": "startrack.catalog",
    "load_catalog": "startrack.catalog",
    "read_image": "startrack.imageio",
    "Status": "startrack.records",
    "ReasonCode": "startrack.records",
    "StarTable": "startrack.records",
    "Match": "startrack.records",
    "Identification": "startrack.records",
    "Attitude": "startrack.records",
    "TrackState": "startrack.records",
    "SolveResult": "startrack.records",
    "to_frame": "startrack.formats.sections",
    "StartrackError": "startrack.errors",
    "BadInputError": "startrack.errors",
    "ParameterError": "startrack.errors",
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name):
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'startrack' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
