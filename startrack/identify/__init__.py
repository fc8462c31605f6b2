"""Lost-in-space star identification: a registry of algorithms and one search driver.

Every algorithm is an :class:`~startrack.identify.algorithm.Algorithm`: a generator
of proposals in its paper's order, a configuration dataclass and the kind of
database it needs.  :func:`identify_stars` runs it through the shared driver
(:func:`startrack.identify.driver.run`), which verifies each proposal until one
passes the false-match gate.

Adding an algorithm is one module defining an ``Algorithm`` and one line in
:data:`BUILTIN` (or, outside startrack, an entry point in the group
``startrack.identify`` naming ``module:ATTRIBUTE``; or :func:`register` at run
time).
"""
from __future__ import annotations

import dataclasses
import importlib
from typing import TYPE_CHECKING

from startrack.identify.params import IdentifyParams
from startrack.records import Identification, Match

# The algorithm interface and the driver load on first use (a blind `solve` needs neither): module attributes
# of :mod:`startrack.identify.algorithm` named here.
_LAZY = {"Algorithm", "NoConfig", "Proposal", "SearchContext"}
if TYPE_CHECKING:
    from startrack.identify.algorithm import Algorithm


def __getattr__(name):
    if name in _LAZY:
        from startrack.identify import algorithm

        return getattr(algorithm, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["Algorithm", "BUILTIN", "IdentifyParams", "Identification", "Match", "NoConfig", "Proposal",
           "RETIRED", "SearchContext", "algorithm_names", "config_fields", "get_algorithm", "identify_stars",
           "make_config", "register", "warm_up"]

# The built-in algorithms, ``module:ATTRIBUTE`` of an Algorithm each (one line per algorithm).
BUILTIN = (
    "startrack.identify.pyramid:PYRAMID",
    "startrack.identify.voting:VOTING",
    "startrack.identify.brightness:BRIGHTNESS",
    "startrack.identify.labelling:LABELLING",
    "startrack.identify.grid:GRID",
    "startrack.identify.modified_pyramid:MODIFIED_PYRAMID",
)
ENTRY_POINT_GROUP = "startrack.identify"

# Names that were algorithms once, with why they went and what to use instead (a clear refusal, not "unknown").
RETIRED = {
    "pyramid-quadratic": "retired: it returned exactly pyramid's answers; use pyramid or modified-pyramid (paper 000)",
}

_registered: dict = {}


def _load(ref: str) -> Algorithm:
    module, _, attr = ref.partition(":")
    alg = getattr(importlib.import_module(module), attr)
    if not isinstance(alg, _algorithm_class()):
        raise TypeError(f"{ref} is not a startrack.identify.Algorithm")
    return alg


def _registry() -> dict:
    if not _registered:
        for ref in BUILTIN:
            alg = _load(ref)
            _registered[alg.name] = alg
        for ep in _entry_points(ENTRY_POINT_GROUP):
            alg = ep.load()
            if isinstance(alg, _algorithm_class()) and alg.name not in _registered:
                _registered[alg.name] = alg
    return _registered


class _EntryPoint:
    """An entry point read by :func:`_entry_points`: ``name``, ``value`` (``module:attribute``) and :meth:`load`,
    as ``importlib.metadata.EntryPoint``."""

    def __init__(self, name: str, value: str, group: str):
        self.name, self.value, self.group = name, value, group

    def load(self):
        module, _, attr = self.value.partition("[")[0].strip().partition(":")
        obj = importlib.import_module(module.strip())
        for part in filter(None, attr.strip().split(".")):
            obj = getattr(obj, part)
        return obj


def _entry_points(group: str) -> list:
    """The entry points of ``group`` of the installed distributions, as ``importlib.metadata.entry_points(group=...)``
    finds them: each ``*.dist-info`` or ``*.egg-info`` directory's ``entry_points.txt`` in the directories of
    ``sys.path``, in order, a distribution's first copy only.  Read directly: importing ``importlib.metadata`` costs a
    process ~20 ms, a tenth of an ``identify`` process's start-up.  A ``sys.path`` entry that is not a directory (a zip
    archive) or a file that cannot be read leaves it to ``importlib.metadata``."""
    import os
    import re
    import sys

    found = []
    seen = set()
    try:
        for entry in sys.path:
            where = entry or "."
            if not os.path.isdir(where):
                if os.path.exists(where):
                    raise OSError(f"{where} is not a directory")
                continue
            for name in sorted(os.listdir(where)):
                if not name.endswith((".dist-info", ".egg-info")):
                    continue
                dist = re.sub(r"[-_.]+", "_", name.rpartition(".")[0].split("-")[0]).lower()
                path = os.path.join(where, name, "entry_points.txt")
                if dist in seen or not os.path.isdir(os.path.join(where, name)):
                    continue
                seen.add(dist)
                if not os.path.isfile(path):
                    continue
                section = None
                with open(path, encoding="utf-8") as fh:
                    for line in fh:
                        line = line.strip()
                        if not line or line.startswith(("#", ";")):
                            continue
                        if line.startswith("[") and line.endswith("]"):
                            section = line[1:-1].strip()
                        elif section == group and "=" in line:
                            key, _, value = line.partition("=")
                            found.append(_EntryPoint(key.strip(), value.strip(), group))
    except (OSError, UnicodeDecodeError):
        from importlib.metadata import entry_points

        return list(entry_points(group=group))
    return found


def _algorithm_class():
    from startrack.identify.algorithm import Algorithm

    return Algorithm


def register(algorithm: Algorithm) -> Algorithm:
    """Add ``algorithm`` to the registry (replacing one of the same name); returns it."""
    if not isinstance(algorithm, _algorithm_class()):
        raise TypeError("register() takes a startrack.identify.Algorithm")
    _registry()[algorithm.name] = algorithm
    return algorithm


def algorithm_names() -> list:
    """Names of every registered algorithm, built-ins first."""
    return list(_registry())


def get_algorithm(name: str) -> Algorithm:
    """The registered algorithm ``name``; ``BadInputError`` naming the parameter ``algorithm`` otherwise."""
    reg = _registry()
    if name not in reg:
        from startrack.errors import BadInputError

        if name in RETIRED:
            raise BadInputError("algorithm", None, f"{name!r} is {RETIRED[name]}")
        raise BadInputError("algorithm", None, f"unknown algorithm {name!r}; choose from {', '.join(reg)}")
    return reg[name]


def warm_up(algorithm: str, db, params: IdentifyParams | None = None, camera=None) -> None:
    """Compile (or load from numba's cache) every kernel ``algorithm`` uses, on a frame made from ``db``.

    Call once after loading a database so that the first real frame's
    ``time_ms`` holds identification only.  The frame: the database's stars
    around its first star, seen by ``camera`` when the frames' camera is known
    (what an algorithm prepares for a sensor, e.g. grid's catalog patterns, is
    then the frames'), else by a 10 deg camera.
    """
    from startrack.camera import Camera
    from startrack.rotations import radec_roll_to_dcm, vector_to_radec

    ra, dec = vector_to_radec(db.star_vector[0])
    dcm = radec_roll_to_dcm(ra, dec, 17.0)
    widest = getattr(db, "max_angle_deg", None) or getattr(db, "fov_deg", 20.0)
    cam = camera if camera is not None else Camera.from_fov(min(10.0, 0.5 * float(widest)), 512, 512)
    body = db.star_vector @ dcm.T
    front = body[:, 2] > 0.9
    x, y = cam.vectors_to_pixels(body[front])
    inside = cam.in_image(x, y)
    stars = [{"x": float(a), "y": float(b), "flux": 1.0e4 * 10 ** (-0.4 * float(m))}
             for a, b, m in zip(x[inside], y[inside], db.star_mag[front][inside])]
    stars.sort(key=lambda s: -s["flux"])
    from startrack.identify.driver import WARMING_UP

    token = WARMING_UP.set(True)
    try:
        identify_stars(stars[:12] if len(stars) >= 3 else stars + [{"x": 1.0, "y": 1.0}] * 3, cam, db, algorithm,
                       params)
        # The final catalog match's kernel (identify's default matches every detection against the catalog).
        from startrack.identify.catalog_match import warm_final_match

        warm_final_match()
    finally:
        WARMING_UP.reset(token)


def database_kind(name: str) -> str:
    """The database kind (``"kvector"``, ``"labels"``) algorithm ``name`` needs."""
    return get_algorithm(name).database


def _field_type(f) -> type:
    """``int``, ``float``, ``bool`` or ``str`` from a field's annotation (``int | None`` -> ``int``)."""
    text = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    for name, kind in (("bool", bool), ("int", int), ("float", float), ("str", str)):
        if name in text.replace("None", "").split("|")[0] or text.strip() == name:
            return kind
    return type(f.default) if f.default is not None else float


def config_fields() -> list:
    """Every configuration field of every registered algorithm.

    Returns
    -------
    list of dict
        ``name`` (the field name), ``type`` (``int``, ``float``, ``bool``,
        ``str``), ``default`` (of the first algorithm that has it), ``help``,
        ``algorithms`` (names of the algorithms that have it).  A front end (the
        command line) offers one setting per entry.
    """
    out: dict = {}
    for alg in _registry().values():
        for f in dataclasses.fields(alg.config):
            entry = out.setdefault(f.name, {"name": f.name, "type": _field_type(f), "default": f.default,
                                            "help": f.metadata.get("help", ""), "algorithms": []})
            entry["algorithms"].append(alg.name)
    return list(out.values())


def make_config(name: str, values: dict | None = None):
    """The configuration of algorithm ``name`` from its defaults and ``values`` (field name -> value).

    A value for a field the algorithm does not have is a ``BadInputError``
    naming the field.
    """
    alg = get_algorithm(name)
    values = {k: v for k, v in (values or {}).items() if v is not None}
    known = {f.name: f for f in dataclasses.fields(alg.config)}
    for k in values:
        if k not in known:
            from startrack.errors import BadInputError

            raise BadInputError(k, None, f"is not a setting of {name} (its settings: {', '.join(known) or 'none'})")
    return alg.config(**values)


_DEFAULT_CONFIGS: dict = {}     # an algorithm's default configuration per configuration type, when frozen


def _default_config(kind: type):
    """``kind()``: made once when ``kind`` is a frozen dataclass (an instance nobody can change is shared)."""
    got = _DEFAULT_CONFIGS.get(kind)
    if got is None:
        got = kind()
        if dataclasses.is_dataclass(kind) and kind.__dataclass_params__.frozen:
            _DEFAULT_CONFIGS[kind] = got
    return got


def identify_stars(stars: list, camera, db, algorithm: str = "pyramid", params: IdentifyParams | None = None,
                   config=None, catalog=None, apparent=None) -> Identification:
    """Identify the stars of one frame.

    Parameters
    ----------
    stars : list of dict or StarTable
        ``x``, ``y`` (pixels), optionally ``flux`` and ``sigma_px`` (px),
        brightest first (as ``centroid`` writes them); a StarTable's columns are
        used as they are.
    camera : Camera
    db : KVectorDatabase or LabelDatabase
        The database kind of the algorithm (:func:`database_kind`).
    algorithm : str
        A registered name (:func:`algorithm_names`).
    params : IdentifyParams, optional
        Shared settings (tolerances, false-match limit, search budget).
    config : dataclass, optional
        The algorithm's own settings (default: its defaults).
    catalog : Catalog, optional
        Match the detections the database does not hold against this catalog
        once the attitude is known (:func:`startrack.identify.catalog_match.match_catalog`).
    apparent : callable, optional
        ``apparent(vectors, parallax_mas)``: ICRS unit vectors to the frame's apparent places
        (:meth:`startrack.apparent.FrameApparent.apparent`): the final match
        and ``quaternion_estimate`` then account for stellar aberration.

    Returns
    -------
    Identification
        ``ok`` with matches (star index -> catalog id) or ``failed`` with a
        reason.  Never raises for an unidentifiable frame.
    """
    alg = get_algorithm(algorithm)
    if config is None:
        config = _default_config(alg.config)
    elif not isinstance(config, alg.config):
        from startrack.errors import BadInputError

        raise BadInputError("config", None, f"{algorithm} takes a {alg.config.__name__}, got {type(config).__name__}")
    run = _RUN[0]
    if run is None:
        from startrack.identify.driver import run

        _RUN[0] = run
    return run(alg, config, stars, camera, db, params or IdentifyParams(), catalog, apparent)


_RUN = [None]   # the driver's run(), imported at the first identification (a blind `solve` never loads it)
