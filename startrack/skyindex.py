"""A sky index of unit vectors: the stars within a cone without testing the whole catalog.

The stars are sorted into ``nb`` bands of equal area (equal steps of ``z``, the sine of the
declination) and, within a band, by right ascension
(:func:`startrack._kernels.sky_index.sky_index`).  A cone query
(:func:`startrack._kernels.sky_index.cone_stars`) visits the bands the cone can reach and, in each,
the right ascensions within the cone's widest extent ``asin(sin r / cos dec)``
(all of them when the cone holds a pole or is wider than a hemisphere's reach),
and tests only those stars: a 15 degree field of the 118,000-star catalog tests about a
thousand.  The answer is the brute-force one, ascending.

Declination bands were measured against HEALPix cone searches (astropy-healpix 2.0.1 at
nside 16-64 and cdshealpix 0.9.0 at depth 4-6, on the shipped catalog): the bands answer a
3 degree cone in 7 us and a 12 degree one in 20 us, the HEALPix packages in 69-193 and
189-2,104 us (their per-call overhead and the cells' look-up), so no dependency is added
(``benchmarks/results/results-speed-2026-12-05.md``).

Example
-------
>>> import numpy as np
>>> from startrack.skyindex import SkyIndex
>>> vec = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
>>> SkyIndex(vec).cone(np.array([0.9, 0.1, 0.0]), np.cos(np.radians(20.0))).tolist()
[0]
"""
from __future__ import annotations

import math

import numpy as np

from startrack.errors import ParameterError

__all__ = ["SkyIndex"]


class SkyIndex:
    """Unit vectors indexed for cone queries (bands of ``z``, right ascension within a band).

    Parameters
    ----------
    vectors : ndarray (n, 3)
        Unit vectors (ICRS); kept by reference and read, never written.
    n_bands : int, optional
        Number of equal-area bands (default about ``sqrt(n)``, 8 to 1024: a band
        then holds about as many stars as there are bands).
    """

    def __init__(self, vectors, n_bands: int | None = None):
        from startrack._kernels.sky_index import sky_index

        vec = np.ascontiguousarray(vectors, dtype=np.float64)
        if vec.ndim != 2 or vec.shape[1] != 3:
            raise ParameterError("vectors", f"must have shape (n, 3), got {vec.shape}", "SkyIndex")
        self.vectors = vec
        nb = n_bands if n_bands is not None else max(8, min(1024, int(math.sqrt(len(vec)))))
        if nb < 1:
            raise ParameterError("n_bands", f"must be at least 1, got {nb}", "SkyIndex")
        self.cells, self.ra = sky_index(vec, int(nb))

    @classmethod
    def from_arrays(cls, vectors, cells, ra) -> SkyIndex:
        """The index of ``vectors`` from the ``cells`` and ``ra`` a :class:`SkyIndex` of them made (a cache's copy),
        checked first: ``ParameterError`` naming the array when the bands' offsets or the stars' rows could make a cone
        query read outside ``vectors`` (a damaged file), or ``ra`` is not one per star."""
        vec = np.ascontiguousarray(vectors, dtype=np.float64)
        cells = np.ascontiguousarray(cells, dtype=np.int64)
        ra = np.ascontiguousarray(ra, dtype=np.float64)
        m = len(vec)
        nb = int(cells[0]) if len(cells) else 0
        if vec.ndim != 2 or vec.shape[1] != 3 or nb < 1 or cells.shape != (nb + 2 + m,):
            raise ParameterError("cells", f"do not index {m} vectors", "SkyIndex.from_arrays")
        ptr, rows = cells[1:nb + 2], cells[nb + 2:]
        if ptr[0] != 0 or ptr[-1] != m or np.any(np.diff(ptr) < 0) or (m and (rows.min() < 0 or rows.max() >= m)):
            raise ParameterError("cells", "hold offsets or rows outside the vectors", "SkyIndex.from_arrays")
        if ra.shape != (m,):
            raise ParameterError("ra", f"must hold one value per vector ({m}), got shape {ra.shape}",
                                 "SkyIndex.from_arrays")
        out = cls.__new__(cls)
        out.vectors, out.cells, out.ra = vec, cells, ra
        return out

    def __len__(self) -> int:
        return len(self.vectors)

    def cone(self, axis, cos_radius: float) -> np.ndarray:
        """The rows ``s`` with ``vectors[s] . axis > cos_radius``, ascending (int64).

        Parameters
        ----------
        axis : array (3,)
            Unit vector of the cone's axis.
        cos_radius : float
            Cosine of the cone's radius (any value: below -1 every star, at or above 1 none).
        """
        from startrack._kernels.sky_index import cone_stars

        ax = np.asarray(axis, dtype=np.float64).reshape(3)
        out = np.empty(len(self.vectors), dtype=np.int64)      # per call: an index may be shared by threads
        k = cone_stars(float(ax[0]), float(ax[1]), float(ax[2]), float(cos_radius), self.vectors, self.cells,
                       self.ra, out)
        return out[:k]

    def near(self, axis, cos_radius: float, slack: float = 1e-9) -> np.ndarray:
        """The rows of :meth:`cone` with ``cos_radius - slack``: a superset of the cone for a caller that
        tests its own inequality on them (the same stars whatever the rounding of its dot products)."""
        return self.cone(axis, cos_radius - slack)
