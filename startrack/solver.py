"""``startrack.Solver``: the public Python API, one object that owns what a session needs.

A :class:`Solver` holds the star catalog, the identification databases and the
camera, loads each the first time it is needed and keeps it for the next call.
There is no module-level state: two solvers share nothing but the on-disk
database cache (:func:`startrack.solve.cache_dir`).

Example
-------
>>> import startrack
>>> solver = startrack.Solver()
>>> result = solver.solve("examples/data/sky.tiff")          # doctest: +SKIP
>>> result.status, result.attitude.ra, result.attitude.dec   # doctest: +SKIP
(<Status.OK: 'ok'>, 286.43..., 28.94...)
"""
from __future__ import annotations

import os

import numpy as np

from startrack.errors import ParameterError

__all__ = ["Solver"]


class Solver:
    """Solve images, identify star lists, estimate and track attitudes.

    Parameters
    ----------
    catalog : Catalog, str or os.PathLike, optional
        The star catalog or its HDF5 file (default: the shipped Hipparcos
        catalog).  Loaded on first use.
    camera : Camera, str or os.PathLike, optional
        The camera (or a ``startrack.camera/1`` file).  :meth:`solve` then
        skips the field-of-view search; :meth:`identify`, :meth:`attitude`
        and :meth:`track` use it when not given one.
    database : KVectorDatabase, LabelDatabase, str or os.PathLike, optional
        The identification database of :meth:`identify` and :meth:`track`
        (default: the cached database of the camera's field-of-view band,
        built on first use).
    algorithm : str
        Identification algorithm (:func:`startrack.identify.algorithm_names`).
    method : str
        Wahba solver of the attitude (``quest``, ``svd``, ``q-method``, ``foam``, ``esoq2``, ``triad``).
    epoch : float, optional
        Epoch of observation (decimal year): catalog positions are propagated
        to it with their proper motions.
    options : SolveOptions, optional
        Settings of :meth:`solve` (time limit, false-match limit, ...).
    """

    def __init__(self, catalog=None, camera=None, database=None, *, algorithm: str = "pyramid",
                 method: str = "quest", epoch: float | None = None, options=None):
        from startrack.solve import SolveOptions

        self._catalog_arg = catalog
        self._catalog = None
        self._camera_arg = camera
        self._camera = None
        self._database_arg = database
        self._database = None
        self.algorithm = algorithm
        self.method = method
        self.epoch = epoch
        self.options = options or SolveOptions(algorithm=algorithm, method=method, epoch=epoch)
        self._bands = None          # the FOV bands' databases, loaded or built once (solve.BandDatabases)
        self._positions_cache: dict = {}
        self._catalog_stars_cache = None

    # ------------------------------------------------------------------ owned resources
    @property
    def catalog(self):
        """The star catalog (:class:`startrack.catalog.Catalog`), loaded on first use."""
        if self._catalog is None:
            from startrack.catalog import Catalog, load_catalog

            arg = self._catalog_arg
            self._catalog = arg if isinstance(arg, Catalog) else load_catalog(
                None if arg is None else os.fspath(arg))
        return self._catalog

    @property
    def camera(self):
        """The camera (:class:`startrack.camera.Camera`) given to the solver, or ``None``."""
        if self._camera is None and self._camera_arg is not None:
            from startrack.camera import Camera

            arg = self._camera_arg
            if isinstance(arg, Camera):
                self._camera = arg
            else:
                from startrack.formats.sections import camera_from_file

                self._camera = camera_from_file(os.fspath(arg))
        return self._camera

    def _positions(self, epoch: float | None = None):
        """Catalog rows by id and ICRS unit vectors at ``epoch`` (default: the solver's), made once per epoch
        (the last few epochs are kept)."""
        epoch = self.epoch if epoch is None else epoch
        if epoch not in self._positions_cache:
            if len(self._positions_cache) > 8:
                self._positions_cache.clear()
            cat = self.catalog if epoch is None else self.catalog.propagate(epoch)
            self._positions_cache[epoch] = (cat.rows_by_id(), cat.vectors())
        return self._positions_cache[epoch]

    def database(self, camera=None):
        """The identification database: the one given, else the cached one of ``camera``'s field-of-view band."""
        if self._database is None and self._database_arg is not None:
            arg = self._database_arg
            if isinstance(arg, (str, os.PathLike)):
                from startrack.identify import database_kind

                if database_kind(self.algorithm) == "labels":
                    from startrack.labels import load_labels as load
                else:
                    from startrack.kvector import load_kvector as load
                arg = load(os.fspath(arg))
            self._database = arg
        if self._database is not None:
            return self._database
        camera = camera if camera is not None else self.camera
        if camera is None:
            raise ParameterError("camera", "is needed to choose a database (give camera or database)", "Solver")
        from startrack.solve import _band_of

        return self.band_database(_band_of(camera.fov_deg[0]))

    @property
    def bands(self):
        """The databases of the FOV bands (:class:`startrack.solve.BandDatabases`), kept in memory."""
        if self._bands is None:
            from startrack.solve import BandDatabases

            given = self.database() if self._database_arg is not None else None
            self._bands = BandDatabases(self.catalog, given)
        return self._bands

    def band_database(self, band: int, which: int = 0):
        """The k-vector database of FOV band ``band`` (:data:`startrack.solve.FOV_BANDS`), kept in memory.

        When the solver was given a database, that one, whatever the band.
        """
        return self.bands.band_database(band, which)

    def band_labels(self, band: int, which: int = 0):
        """The label database (paper 004) of FOV band ``band``, kept in memory."""
        return self.bands.band_labels(band, which)

    # ------------------------------------------------------------------ stages
    def solve(self, image, fov_deg: float | None = None, *, camera=None, saturation: float | None = None,
              ra_deg: float | None = None, dec_deg: float | None = None, radius_deg: float | None = None,
              fov_min_deg: float | None = None, fov_max_deg: float | None = None, target_pixels=(),
              target_radec=()):
        """Solve one image: centroid, identify and attitude, with an unknown field of view.

        Parameters
        ----------
        image : str, os.PathLike or ndarray (height, width)
            An image file (TIFF, PNG, FITS, JPEG, ...) or its pixels, row 0 at the top.
        fov_deg : float, optional
            Horizontal field of view hint, degrees (searched within
            ``options.fov_tolerance``).  Default: unknown (the blind search covers about 2 to 70 degrees,
            as ``startrack solve``).
        camera : Camera, optional
            A calibrated camera (default: the solver's): no field-of-view search.
        saturation : float, optional
            Saturation level in DN (read from the file for a path; for uint8 and uint16 pixels their type's
            largest value, as the file's).  A flat plateau at the image's largest value is clipping too, given
            or not (:func:`startrack.centroid.find_stars`): the answer is the CLI's for the same pixels.
        ra_deg, dec_deg, radius_deg : float, optional
            The boresight lies within ``radius_deg`` of ``(ra_deg, dec_deg)`` (ICRS, degrees; all three or
            none): the search skips patterns elsewhere, and refuses a solution outside the circle.
        fov_min_deg, fov_max_deg : float, optional
            The horizontal field of view lies between them (degrees; instead of ``fov_deg``).
        target_pixels : sequence of (x, y), optional
            Pixels whose sky positions go into ``result.targets``.
        target_radec : sequence of (ra, dec), optional
            Sky positions (degrees) whose pixels go into ``result.targets``.

        Returns
        -------
        SolveResult
            ``status`` ``"ok"`` with ``attitude`` (boresight ``ra``, ``dec``
            and ``roll`` in degrees; quaternion scalar last, ICRS to camera),
            the fitted ``camera`` and ``fov_deg``, and astropy views (``wcs``,
            ``center``, ``matches``, ``pixel_to_world``, ``world_to_pixel``);
            else ``"failed"`` with ``reason`` and ``reason_code`` (a hint
            that excluded the answer is named in ``reason``).

        Raises
        ------
        BadInputError
            An unreadable file or an image that is not 2-D.
        ParameterError
            A hint out of range, or ``ra_deg``/``dec_deg``/``radius_deg`` not all given.
        """
        import dataclasses

        from startrack.solve import solve_image

        opts = self.options
        if fov_deg is not None:
            if not 0 < fov_deg < 90:
                raise ParameterError("fov_deg", f"must be in (0, 90) degrees, got {fov_deg}", "Solver.solve")
            opts = dataclasses.replace(opts, fov_deg=fov_deg)
        given = {k: v for k, v in (("ra_deg", ra_deg), ("dec_deg", dec_deg), ("radius_deg", radius_deg),
                                   ("fov_min_deg", fov_min_deg), ("fov_max_deg", fov_max_deg)) if v is not None}
        if target_pixels:
            given["target_pixels"] = tuple((float(x), float(y)) for x, y in target_pixels)
        if target_radec:
            given["target_radec"] = tuple((float(r), float(d)) for r, d in target_radec)
        if given:
            opts = dataclasses.replace(opts, **given)      # SolveOptions checks them (ParameterError)
        return solve_image(image, opts, camera=camera if camera is not None else self.camera, catalog=self.catalog,
                           saturation=saturation, databases=self.bands)

    def _catalog_stars(self):
        """The catalog at the solver's epoch as :class:`startrack.identify.catalog_match.CatalogStars`, made once."""
        got = self._catalog_stars_cache
        if got is None or got[0] != self.epoch:
            from startrack.identify.catalog_match import CatalogStars

            cat = self.catalog if self.epoch is None else self.catalog.propagate(self.epoch)
            got = self._catalog_stars_cache = (self.epoch, CatalogStars.from_catalog(cat))
        return got[1]

    def identify(self, stars, camera=None, *, algorithm: str | None = None, params=None, match_all: bool = True):
        """Identify the stars of one frame.

        The same identification as ``startrack identify`` with the solver's catalog
        (``--catalog``) and ``match_all`` (``--match-all``, its default).

        Parameters
        ----------
        stars : StarTable or list of dict
            Centroids in pixels (``x`` column, ``y`` row), brightest first.
        camera : Camera, optional
            Default: the solver's.
        algorithm : str, optional
            Default: the solver's.
        params : IdentifyParams, optional
            Tolerances and limits.
        match_all : bool
            After the attitude, match the detections the database lacks to the
            solver's catalog (:func:`startrack.identify.catalog_match.match_catalog`);
            ``False``: the database's stars only.

        Returns
        -------
        Identification
            ``matches`` pair star indices with catalog ids; ``status``
            ``"failed"`` with ``reason`` when the frame cannot be identified.
        """
        from startrack.formats.sections import identification_record
        from startrack.identify import identify_stars

        camera = self._need_camera(camera, "identify")
        algorithm = algorithm or self.algorithm
        db = self.database(camera)
        from startrack.records import StarTable

        res = identify_stars(stars if isinstance(stars, StarTable) else list(stars), camera, db, algorithm, params,
                             catalog=self._catalog_stars() if match_all else None)
        return identification_record(res)

    def attitude(self, stars, identification, camera=None, *, method: str | None = None,
                 epoch: float | None = None, sigma_px: float | None = None):
        """The attitude from identified stars (Wahba's problem, paper 000 Eq. 15, with outlier rejection).

        Parameters
        ----------
        stars : StarTable or list of dict
            Centroids in pixels; ``sigma_px`` (1-sigma per axis) weights them when present.
        identification : Identification
            Which star is which catalog star.
        camera : Camera, optional
            Default: the solver's.
        method : str, optional
            Wahba solver; default the solver's.
        epoch : float, optional
            Epoch of observation (decimal year); default the solver's.
        sigma_px : float, optional
            Centroid 1-sigma for every star, pixels (default: each star's
            ``sigma_px``, else 0.5 px, as ``startrack attitude``; never below 0.05 px).

        Returns
        -------
        Attitude
            ``quaternion`` (scalar last, ICRS to camera), boresight ``ra``,
            ``dec`` and ``roll`` (degrees), covariance (arcsec^2, camera
            axes); or ``"failed"`` with a reason.
        """
        from startrack.formats.sections import identification_record
        from startrack.records import StarTable
        from startrack.solve import identified_attitude

        camera = self._need_camera(camera, "attitude")
        table = stars if isinstance(stars, StarTable) else StarTable.from_list(list(stars))
        rows, vec = self._positions(epoch)
        return identified_attitude(table, identification_record(identification), camera, rows, vec,
                                   method or self.method, sigma_px,
                                   epoch if epoch is not None else self.epoch)

    def track(self, frames, camera=None, *, dt_s: float = 1.0, times=None, config=None, initial_attitude=None):
        """Track the attitude through a sequence of images.

        Parameters
        ----------
        frames : iterable of str, os.PathLike or ndarray
            Images in time order (read lazily, one at a time).
        camera : Camera, optional
            Default: the solver's (required).
        dt_s : float
            Time between frames, seconds, when ``times`` is not given.
        times : iterable of float, optional
            Frame times, seconds.
        config : TrackerConfig, optional
        initial_attitude : Attitude or ndarray (3, 3), optional
            Skip the first lost-in-space solution.

        Yields
        ------
        TrackState
            One per frame: ``mode``, rate, ... with the frame's ``stars``,
            ``identification`` and ``attitude`` attached.
        """
        from startrack.formats.sections import from_section, identification_record
        from startrack.records import Attitude, StarTable, TrackState
        from startrack.track import Tracker

        camera = self._need_camera(camera, "track")
        dcm = initial_attitude.dcm if isinstance(initial_attitude, Attitude) else initial_attitude
        tracker = Tracker(self.catalog, camera, self.database(camera), config, dcm)
        times = iter(times) if times is not None else None
        for k, frame in enumerate(frames):
            image, saturation = _read(frame)
            t = next(times) if times is not None else k * dt_s
            out = tracker.step(image, float(t), saturation)
            state = from_section(TrackState, out["track"], "track")
            state.star_table = StarTable.from_list(out["stars"]) if out.get("stars") else StarTable.empty()
            if out.get("identification") is not None:
                state.identification = identification_record(out["identification"])
            state.attitude = from_section(Attitude, out["attitude"], "attitude")
            yield state

    def _need_camera(self, camera, what):
        camera = camera if camera is not None else self.camera
        if camera is None:
            raise ParameterError("camera", "is needed (give it here or to Solver)", f"Solver.{what}")
        return camera


def _read(frame):
    if isinstance(frame, (str, os.PathLike)):
        from startrack.imageio import read_image

        image, meta = read_image(os.fspath(frame))
        return image, meta["saturation"]
    return np.asarray(frame), None
