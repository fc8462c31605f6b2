"""Image parity: a mirrored image (flipped by a diagonal mirror, or stored bottom-up) seen as a camera's.

A mirrored image's stars are an ordinary camera's flipped about the principal point's column:
``x -> 2 cx - x`` turns them back (a flip of the rows is this flip and half a turn about the
boresight, so one flip covers both).  The search identifies the flipped list; the attitude is then
the un-mirrored camera's (whose pixel ``(2 cx - x, y)`` is the image's ``(x, y)``), and the WCS of
the image has a ``CD`` matrix of the other determinant sign.
"""
from __future__ import annotations

from startrack.errors import ParameterError

PARITIES = ("auto", "normal", "mirrored")
"""``auto``: normal first, mirrored only when normal finds nothing."""

__all__ = ["PARITIES", "parities_to_try", "mirror_stars", "identify_either_parity"]


def parities_to_try(parity: str) -> tuple:
    """The parities searched, in order, for a ``parity`` setting."""
    if parity not in PARITIES:
        raise ParameterError("parity", f"must be one of {', '.join(PARITIES)}, got {parity!r}")
    return ("normal", "mirrored") if parity == "auto" else (parity,)


def mirror_stars(stars, cx: float):
    """The star list (dicts with ``x``) flipped about column ``cx``: ``x -> 2 cx - x``, other keys kept."""
    return [{**s, "x": 2.0 * cx - float(s["x"])} for s in stars]


def identify_either_parity(stars, camera, db, algorithm: str = "pyramid", params=None, config=None, catalog=None,
                           parity: str = "auto", apparent=None):
    """:func:`startrack.identify.identify_stars` over the parities of ``parity``: ``(result, parity searched last)``.

    ``auto`` searches the mirrored stars only when the normal ones found nothing, within what is
    left of ``params.max_time_ms`` (a frame that fails costs at most the one budget), and each
    parity gets half the false-match budget (two parities are two hypotheses).  The result's
    matches index ``stars`` as given (flipping keeps the order).
    """
    import dataclasses

    from startrack.identify import IdentifyParams, identify_stars

    params = params or IdentifyParams()
    order = parities_to_try(parity)
    shared = dataclasses.replace(params, max_false_probability=params.max_false_probability / len(order))
    result = None
    searched = order[0]
    spent_ms, trials = 0.0, 0
    for searched in order:
        left = params.max_time_ms - spent_ms
        if result is not None and left <= 0:
            break
        listed = stars if searched == "normal" else mirror_stars(stars, camera.cx)
        result = identify_stars(listed, camera, db, algorithm, dataclasses.replace(shared, max_time_ms=left), config,
                                catalog, apparent)
        # Each search's own time (its database loading excluded, as identify_stars counts it).
        spent_ms += result.time_ms or 0.0
        trials += result.trials or 0
        if result.status == "ok":
            break
    if len(order) > 1 and searched != order[0]:
        result.time_ms, result.trials = spent_ms, trials
    if result.status == "ok":
        result.parity = searched
    elif len(order) > 1 and searched != order[0]:
        result.reason = f"{result.reason} (either parity)"
    return result, searched
