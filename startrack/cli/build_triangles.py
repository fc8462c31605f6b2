"""startrack build-triangles: paper 000's triangle database."""
import click

from startrack.cli.options import (
    CAMERA_EXCLUSIVE,
    Command,
    FiniteFloat,
    camera_from_options,
    camera_options,
    catalog_option,
    handle_errors,
    info,
    mag_options,
    quiet_option,
)


@click.command("build-triangles", cls=Command, exclusive=CAMERA_EXCLUSIVE, ordered=[("mag_min", "mag_max")],
               short_help="Build paper 000's triangle database (modified pyramid).")
@catalog_option
@camera_options
@mag_options(max_help="Faintest catalog star used (default: all of the catalog).")
@click.option("--max-separation-deg", type=FiniteFloat(0, 90, min_open=True), default=None,
              help="Longest triangle side kept (default: the field's shorter side, paper 000's reading).")
@click.option("--merge-px", type=FiniteFloat(0, 100), default=None,
              help="Stars closer than this many pixels are one entry (unresolved double; default 2, 0 = off).")
@click.option("--epoch", type=FiniteFloat(1000, 3000), default=None, help="Propagate proper motion to this epoch first.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False), help="Database file (.h5).")
@quiet_option
@handle_errors
def command(catalog, camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2, mag_max, mag_min,
            max_separation_deg, merge_px, epoch, output, quiet):
    """Build the triangle database of paper 000's modified pyramid (startrack.triangles/1).

    Every triple of catalog stars whose three sides are shorter than the
    largest separation, with the three internal angles of its triangle (paper
    000 Eq. 2, Table 4), sorted by the smallest angle, with Mortari's k-vector
    and paper 000's fitted quadratic (Eqs. 7-12) for the look-up.  Use it with
    `startrack identify --algorithm modified-pyramid`.

    Unresolved doubles: stars closer than --merge-px (default 2 px, where
    render blends two stars) become one entry at their photocentre with the
    brighter star's id, as in build-kvector: the sensor sees one star there,
    and a database holding both would name either.

    \b
    Example (paper 000: 8 x 8 deg, Hp 2.5 to 6.59):
      startrack build-triangles --fov-deg 8 --size 1024x1024 --mag-min 2.5 --mag-max 6.59 -o tri.h5
    """
    import os

    from startrack.catalog import DEFAULT_MERGE_PX, load_catalog, merge_radius_arcsec
    from startrack.errors import BadInputError
    from startrack.formats.atomic import check_writable
    from startrack.progress import ProgressBar
    from startrack.triangles import build_triangles, save_triangles

    if os.path.splitext(output)[1].lower() not in (".h5", ".hdf5"):
        raise BadInputError(output, None, "the database is HDF5: give a .h5 or .hdf5 name")
    check_writable(output)
    cam = camera_from_options(camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2,
                              default_size="1024x1024")
    if max_separation_deg is None:
        max_separation_deg = min(cam.fov_deg)
    if not 0 < max_separation_deg <= 90:
        raise BadInputError("--max-separation-deg", None, f"must be in (0, 90], got {max_separation_deg:g}")
    cat = load_catalog(catalog).filter_magnitude(mag_min, mag_max)
    if epoch is not None:
        cat = cat.propagate(epoch)
    merge_arcsec = merge_radius_arcsec(cam, DEFAULT_MERGE_PX if merge_px is None else merge_px) if merge_px != 0 else 0.0
    if merge_arcsec:
        cat = cat.merge_close(merge_arcsec)
    params = {"catalog": catalog or "shipped", "camera": cam.to_dict(), "mag_min": mag_min, "mag_max": mag_max,
              "epoch": epoch, "merge_arcsec": merge_arcsec or None,
              "merged_stars": sum(len(v) for v in (getattr(cat, "merged", {}) or {}).values())}
    db = build_triangles(cat, max_separation_deg, progress=ProgressBar("build-triangles", quiet), params=params)
    save_triangles(db, output)
    info(quiet, f"build-triangles: {db.n_stars} stars, {db.n_triangles} triangles with sides up to "
                f"{max_separation_deg:.2f} deg, {os.path.getsize(output) / 1e6:.2f} MB, "
                f"{db.params['build_seconds']:.2f} s -> {output}")
