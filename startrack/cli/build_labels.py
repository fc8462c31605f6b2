"""startrack build-labels: paper 004's label database."""
import click

from startrack.cli.options import (
    Command,
    FiniteFloat,
    Int,
    catalog_option,
    handle_errors,
    info,
    mag_options,
    quiet_option,
)


@click.command("build-labels", cls=Command, ordered=[("group_size", "stars_per_field")], short_help="Build the labelling database (paper 004) for a field of view.")
@catalog_option
@click.option("--fov-deg", type=FiniteFloat(0, 90, min_open=True), required=True, help="Field of view (degrees).")
@mag_options(max_help="Faintest catalog star (paper 004: 5.2).", with_min=False)
@click.option("--merge-arcsec", type=FiniteFloat(0, 3600, min_open=True), default=None, help="Merge closer stars first (they image as one).")
@click.option("--stars-per-field", type=Int(3, 30), default=8, show_default=True, help="Brightest stars per field.")
@click.option("--group-size", type=Int(3, 8), default=4, show_default=True, help="Stars per labelled group.")
@click.option("--scale-digits", "scale_digits", type=Int(1, 6), default=2, show_default=True, help="r: sub-label digits.")
@click.option("--step-deg", type=FiniteFloat(0.1, 90), default=1.0, show_default=True, help="Boresight sweep step.")
@click.option("--epoch", type=FiniteFloat(1000, 3000), default=None, help="Propagate proper motion to this epoch first.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False), help="Database file (.h5).")
@quiet_option
@handle_errors
def command(catalog, fov_deg, mag_max, merge_arcsec, stars_per_field, group_size, scale_digits, step_deg, epoch,
            output, quiet):
    """Build the label database of the labelling identification (startrack.labels/1).

    Sweeps boresights over the sphere, takes the brightest stars of each field
    and every group of them, and stores their distance-ratio labels (paper 004
    Eqs. 1-3) sorted, with a trend line for look-ups.

    \b
    Example (paper 004's sensor: 24 deg, magnitude 5.2, 8 stars, groups of 4):
      startrack build-labels --fov-deg 24 --mag-max 5.2 -o p004-labels.h5
    """
    import os

    from startrack.catalog import load_catalog
    from startrack.errors import BadInputError
    from startrack.formats.atomic import check_writable
    from startrack.labels import build_labels, save_labels
    from startrack.progress import ProgressBar

    if os.path.splitext(output)[1].lower() not in (".h5", ".hdf5"):
        raise BadInputError(output, None, "the database is HDF5: give a .h5 or .hdf5 name")
    check_writable(output)
    if not 0 < fov_deg <= 90:
        raise BadInputError("--fov-deg", None, f"must be in (0, 90], got {fov_deg:g}")
    cat = load_catalog(catalog, mag_max=mag_max).filter_magnitude(None, mag_max)
    if epoch is not None:
        cat = cat.propagate(epoch)
    if merge_arcsec:
        cat = cat.merge_close(merge_arcsec)
    if len(cat) == 0:
        raise BadInputError("--mag-max", None, "no star is left after filtering")
    params = {"catalog": catalog or "shipped", "mag_max": mag_max, "merge_arcsec": merge_arcsec, "epoch": epoch}
    db = build_labels(cat, fov_deg, stars_per_field, group_size, scale_digits, step_deg,
                      progress=ProgressBar("build-labels", quiet), params=params)
    save_labels(db, output)
    info(quiet, f"build-labels: {db.params['combinations']} groups ({db.params['distinct_labels']} distinct labels) "
                f"from {db.params['boresights']} boresights, {os.path.getsize(output) / 1e6:.2f} MB, "
                f"{db.params['build_seconds']:.2f} s -> {output}")
