"""startrack build-kvector: the star-pair database with Mortari's k-vector."""
import click

from startrack.cli.options import (camera_from_options, camera_options, catalog_option, handle_errors, info,
                                   quiet_option)


@click.command("build-kvector", short_help="Build the star-pair k-vector database for a sensor.")
@catalog_option
@camera_options
@click.option("--mag-max", type=float, default=None,
              help="Faintest catalog star used.  Without --mag-max/--mag-min the depth is chosen for the sensor.")
@click.option("--mag-min", type=float, default=None, help="Brightest catalog star used.")
@click.option("--stars-per-field", type=float, default=None,
              help="Chosen depth: database stars wanted per field (default 20, lowered to fit --max-pairs).")
@click.option("--max-pairs", type=int, default=None,
              help="Chosen depth: pair budget (default 4,000,000: about 50 MB).")
@click.option("--merge-px", type=float, default=None,
              help="Stars closer than this many pixels are one entry (unresolved double; default 2, 0 = off; "
                   "needs the sensor's pixels: --size or --camera).")
@click.option("--merge-arcsec", type=float, default=None, help="As --merge-px, in arcsec (overrides it).")
@click.option("--margin-deg", type=float, default=0.5, show_default=True,
              help="Added to the diagonal field to give the largest pair separation kept.")
@click.option("--epoch", type=float, default=None, help="Propagate proper motion to this epoch first.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False), help="Database file (.h5).")
@quiet_option
@handle_errors
def command(catalog, camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2, mag_max, mag_min,
            stars_per_field, max_pairs, merge_px, merge_arcsec, margin_deg, epoch, output, quiet):
    """Build the pair database identify uses (startrack.kvector/1).

    All catalog star pairs closer than the sensor's diagonal field plus a margin,
    sorted by the cosine of their angle, with Mortari's k-vector (paper 003
    Eqs. 11-14), paper 000's quadratic search (Eqs. 7-12), pairs in
    brighter/dimmer order (paper 003 Sec. 4.2.1), per-star neighbour lists and
    the star table.  With only --fov-deg the field is taken as square.

    Unresolved doubles: when the sensor's pixels are known, stars closer than
    --merge-px (default 2 px, the separation at which render blends two stars)
    become one entry at their photocentre with their summed flux and the
    brighter star's id; the others are listed in the file as merged.

    Depth: without --mag-max/--mag-min the builder chooses it: a magnitude
    limit at which 95 % of the sky holds --stars-per-field stars per field, and
    a uniform thinning (the brightest stars of each sky cell of half the
    field's short side), lowered if needed to fit --max-pairs.  The chosen
    values are recorded in the file's params.

    \b
    Example (depth chosen for a 6 x 4.5 deg, 1392 x 1040 sensor):
      startrack build-kvector --fov-deg 6 --size 1392x1040 -o narrow.h5
    \b
    Example (paper 003's sensor: 20 x 20 deg, stars to magnitude 5.0):
      startrack build-kvector --fov-deg 20 --mag-max 5.0 -o p003.h5
    \b
    Example (paper 000's camera: f = 41.1 mm, 6 um pixels, 752 x 480, Hp 2.5 to 6.59):
      startrack build-kvector --focal-length-mm 41.1 --pixel-pitch-um 6 --size 752x480 \\
          --mag-min 2.5 --mag-max 6.59 -o p000.h5
    """
    import os
    import time

    import numpy as np

    from startrack.catalog import DEFAULT_MERGE_PX, load_catalog, merge_radius_arcsec
    from startrack.errors import BadInputError
    from startrack.formats.atomic import check_writable
    from startrack.kvector import (DEFAULT_MAX_PAIRS, DEFAULT_STARS_PER_FIELD, build_kvector,
                                   choose_database_stars, max_separation_deg, save_kvector)
    from startrack.progress import ProgressBar

    t0 = time.perf_counter()
    if os.path.splitext(output)[1].lower() not in (".h5", ".hdf5"):
        raise BadInputError(output, None, "the database is HDF5: give a .h5 or .hdf5 name")
    check_writable(output)
    if fov_deg is not None and size is None and camera_file is None and focal_length_mm is None:
        if not 0 < fov_deg <= 90:
            raise BadInputError("--fov-deg", None, f"must be in (0, 90], got {fov_deg:g}")
        cam = None
        max_angle = max_separation_deg(fov_deg, margin_deg=margin_deg)
        field_deg = (fov_deg, fov_deg)
    else:
        cam = camera_from_options(camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2)
        if not 0 < max(cam.fov_deg) <= 90:
            raise BadInputError("--fov-deg", None, f"field of view must be in (0, 90] deg, got {max(cam.fov_deg):.2f}")
        max_angle = max_separation_deg(camera=cam, margin_deg=margin_deg)
        field_deg = tuple(cam.fov_deg)
    auto = mag_max is None and mag_min is None
    if not auto and (stars_per_field is not None or max_pairs is not None):
        raise BadInputError("--stars-per-field", None, "chooses the depth: give it without --mag-max/--mag-min")
    if merge_px is not None and merge_px < 0:
        raise BadInputError("--merge-px", None, f"must be >= 0, got {merge_px:g}")
    if merge_arcsec is not None and not merge_arcsec >= 0:
        raise BadInputError("--merge-arcsec", None, f"must be >= 0, got {merge_arcsec:g}")
    if merge_arcsec is None:
        if cam is not None and merge_px != 0:
            merge_arcsec = merge_radius_arcsec(cam, DEFAULT_MERGE_PX if merge_px is None else merge_px)
        elif merge_px:
            raise BadInputError("--merge-px", None, "needs the sensor's pixels: give --size or --camera")
    cat = load_catalog(catalog, mag_max=mag_max).filter_magnitude(mag_min, mag_max)
    if epoch is not None:
        cat = cat.propagate(epoch)
    if merge_arcsec:
        cat = cat.merge_close(merge_arcsec)
    if auto:
        cat = choose_database_stars(cat, field_deg[0], field_deg[1], max_angle,
                                    DEFAULT_STARS_PER_FIELD if stars_per_field is None else stars_per_field,
                                    max_pairs=DEFAULT_MAX_PAIRS if max_pairs is None else max_pairs)
    if len(cat) < 2:
        raise BadInputError("--mag-min/--mag-max", None, f"{len(cat)} star(s) left after filtering: nothing to pair")
    params = {"catalog": catalog or "shipped", "fov_deg": fov_deg, "margin_deg": margin_deg,
              "camera": cam.to_dict() if cam else None, "mag_min": mag_min, "mag_max": mag_max, "epoch": epoch,
              "merge_arcsec": merge_arcsec or None, "merged_groups": cat.params.get("merged_groups", 0),
              "depth": "chosen" if auto else "given"}
    if auto:
        params.update({k: cat.params[k] for k in ("depth_mag_max", "uniform_per_cell", "uniform_cell_deg",
                                                  "stars_per_field", "stars_per_field_wanted", "sky_fraction",
                                                  "estimated_pairs", "max_pairs")})
    if auto and cam is not None:
        from startrack.catalog import field_statistics

        # Database stars per field over 500 random attitudes (seeded: the same file every time).
        counts = field_statistics(cat, cam, 500, np.random.default_rng(0)).counts
        params.update(field_stars_p5=float(np.percentile(counts, 5)), field_stars_median=float(np.median(counts)))
    db = build_kvector(cat, max_angle, progress=ProgressBar("build-kvector", quiet), params=params)
    db.params["total_seconds"] = round(time.perf_counter() - t0, 3)
    save_kvector(db, output)
    depth = ""
    if auto:
        depth = (f", depth chosen: Hp <= {params['depth_mag_max']:.2f}, {params['uniform_per_cell']} per "
                 f"{params['uniform_cell_deg']:.2f} deg cell")
        if "field_stars_p5" in params:
            depth += (f" (stars per field: median {params['field_stars_median']:g}, "
                      f"5th percentile {params['field_stars_p5']:g})")
    merged = f", {params['merged_groups']} unresolved groups merged" if merge_arcsec else ""
    info(quiet, f"build-kvector: {db.n_stars} stars, {db.n_pairs} pairs up to {max_angle:.2f} deg{depth}{merged}, "
                f"{os.path.getsize(output) / 1e6:.2f} MB, {time.perf_counter() - t0:.2f} s -> {output}")
