"""Lost-in-space star identification: one signature, a registry by name.

Every algorithm is a ``propose(b, db, eps, params, stars, camera) -> Proposal``
function; :func:`identify_stars` runs it and the shared verification
(:mod:`startrack.identify.base`).  Adding an algorithm is adding a module and
an entry in :data:`ALGORITHMS`.
"""
from __future__ import annotations

from startrack.identify.base import IdentifyParams, IdentifyResult

__all__ = ["ALGORITHMS", "DATABASE_KIND", "IdentifyParams", "IdentifyResult", "identify_stars", "algorithm_names"]

# name -> (module, function, database kind)
ALGORITHMS = {
    "pyramid": ("startrack.identify.pyramid", "propose_pyramid", "kvector"),
    "pyramid-quadratic": ("startrack.identify.pyramid", "propose_pyramid_quadratic", "kvector"),
    "voting": ("startrack.identify.voting", "propose_voting", "kvector"),
    "brightness": ("startrack.identify.brightness", "propose_brightness", "kvector"),
    "labelling": ("startrack.identify.labelling", "propose_labelling", "labels"),
    "grid": ("startrack.identify.grid", "propose_grid", "kvector"),
}
DATABASE_KIND = {name: kind for name, (_, _, kind) in ALGORITHMS.items()}


def algorithm_names():
    return list(ALGORITHMS)


def identify_stars(stars: list, camera, db, algorithm: str = "pyramid", params: IdentifyParams | None = None
                   ) -> IdentifyResult:
    """Identify the stars of one frame.

    Parameters
    ----------
    stars : list of dict
        ``x``, ``y`` (pixels), brightest first (as ``centroid`` writes them).
    camera : Camera
    db : KVectorDatabase (or the algorithm's database kind)
    algorithm : str
        A key of :data:`ALGORITHMS`.

    Returns
    -------
    IdentifyResult
        ``status`` ``"ok"`` with matches (star index -> catalog id), or
        ``"failed"`` with a reason.  Never raises for an unidentifiable frame.
    """
    import importlib

    from startrack.errors import ParameterError
    from startrack.identify.base import run

    if algorithm not in ALGORITHMS:
        raise ParameterError("algorithm", f"unknown algorithm {algorithm!r}; choose from {', '.join(ALGORITHMS)}")
    module, func, _ = ALGORITHMS[algorithm]
    propose = getattr(importlib.import_module(module), func)
    return run(algorithm, propose, stars, camera, db, params or IdentifyParams())
