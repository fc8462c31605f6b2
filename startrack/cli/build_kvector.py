"""startrack build-kvector: the star-pair database with Mortari's k-vector."""
import click

from startrack.cli.options import (camera_from_options, camera_options, catalog_option, handle_errors, info,
                                   quiet_option)


@click.command("build-kvector", short_help="Build the star-pair k-vector database for a sensor.")
@catalog_option
@camera_options
@click.option("--mag-max", type=float, default=None, help="Faintest catalog star used (default: all of the catalog).")
@click.option("--mag-min", type=float, default=None, help="Brightest catalog star used.")
@click.option("--margin-deg", type=float, default=0.5, show_default=True,
              help="Added to the diagonal field to give the largest pair separation kept.")
@click.option("--epoch", type=float, default=None, help="Propagate proper motion to this epoch first.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False), help="Database file (.h5).")
@quiet_option
@handle_errors
def command(catalog, camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2, mag_max, mag_min,
            margin_deg, epoch, output, quiet):
    """Build the pair database identify uses (startrack.kvector/1).

    All catalog star pairs closer than the sensor's diagonal field plus a margin,
    sorted by the cosine of their angle, with Mortari's k-vector (paper 003
    Eqs. 11-14), paper 000's quadratic search (Eqs. 7-12), pairs in
    brighter/dimmer order (paper 003 Sec. 4.2.1), per-star neighbour lists and
    the star table.  With only --fov-deg the field is taken as square.

    \b
    Example (paper 003's sensor: 20 x 20 deg, stars to magnitude 5.0):
      startrack build-kvector --fov-deg 20 --mag-max 5.0 -o p003.h5
    \b
    Example (paper 000's camera: f = 41.1 mm, 6 um pixels, 752 x 480, Hp 2.5 to 6.59):
      startrack build-kvector --focal-length-mm 41.1 --pixel-pitch-um 6 --size 752x480 \\
          --mag-min 2.5 --mag-max 6.59 -o p000.h5
    """
    import os

    from startrack.catalog import load_catalog
    from startrack.errors import BadInputError
    from startrack.formats.atomic import check_writable
    from startrack.kvector import build_kvector, max_separation_deg, save_kvector
    from startrack.progress import ProgressBar

    if os.path.splitext(output)[1].lower() not in (".h5", ".hdf5"):
        raise BadInputError(output, None, "the database is HDF5: give a .h5 or .hdf5 name")
    check_writable(output)
    if fov_deg is not None and size is None and camera_file is None and focal_length_mm is None:
        if not 0 < fov_deg <= 90:
            raise BadInputError("--fov-deg", None, f"must be in (0, 90], got {fov_deg:g}")
        cam = None
        max_angle = max_separation_deg(fov_deg, margin_deg=margin_deg)
    else:
        cam = camera_from_options(camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2)
        if not 0 < max(cam.fov_deg) <= 90:
            raise BadInputError("--fov-deg", None, f"field of view must be in (0, 90] deg, got {max(cam.fov_deg):.2f}")
        max_angle = max_separation_deg(camera=cam, margin_deg=margin_deg)
    cat = load_catalog(catalog).filter_magnitude(mag_min, mag_max)
    if epoch is not None:
        cat = cat.propagate(epoch)
    if len(cat) < 2:
        raise BadInputError("--mag-min/--mag-max", None, f"{len(cat)} star(s) left after filtering: nothing to pair")
    params = {"catalog": catalog or "shipped", "fov_deg": fov_deg, "margin_deg": margin_deg,
              "camera": cam.to_dict() if cam else None, "mag_min": mag_min, "mag_max": mag_max, "epoch": epoch}
    db = build_kvector(cat, max_angle, progress=ProgressBar("build-kvector", quiet), params=params)
    save_kvector(db, output)
    info(quiet, f"build-kvector: {db.n_stars} stars, {db.n_pairs} pairs up to {max_angle:.2f} deg, "
                f"{os.path.getsize(output) / 1e6:.2f} MB, {db.params['build_seconds']:.2f} s -> {output}")
