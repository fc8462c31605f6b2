"""startrack catalog-filter: select, propagate, merge and thin catalog stars."""
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


@click.command("catalog-filter", cls=Command, ordered=[("mag_min", "mag_max")], short_help="Select catalog stars by magnitude; propagate, merge, thin.")
@catalog_option
@mag_options(max_help="Keep stars at most this faint (e.g. 6.59).", min_help="Keep stars at least this faint (e.g. 2.5).")
@click.option("--epoch", type=FiniteFloat(1000, 3000), default=None,
              help="Propagate proper motion to this epoch (decimal year, e.g. 2026.9).")
@click.option("--merge-arcsec", type=FiniteFloat(0, 3600, min_open=True), default=None,
              help="Merge stars closer than this (arcsec) into one of combined brightness.")
@click.option("--uniform", type=Int(1), default=None,
              help="Thin to a near-uniform density: keep the N brightest per sky cell.")
@click.option("--cell-deg", type=FiniteFloat(0, 90, min_open=True), default=4.0, show_default=True, help="Sky cell size for --uniform.")
@click.option("--output", "-o", default="-", show_default=True, type=click.Path(dir_okay=False, allow_dash=True),
              help="Output: .h5/.hdf5 (startrack.catalog/1) or .csv; - writes CSV to stdout.")
@quiet_option
@handle_errors
def command(catalog, mag_min, mag_max, epoch, merge_arcsec, uniform, cell_deg, output, quiet):
    """Filter the star catalog for a sensor and write it as HDF5 or CSV.

    Steps run in this order: magnitude range, proper motion to --epoch, merging
    of close stars, uniform thinning.  A one-line summary goes to stderr.

    \b
    Example (paper 000's catalog: Hp 2.5 to 6.59, positions for late 2026):
      startrack catalog-filter --mag-min 2.5 --mag-max 6.59 --epoch 2026.9 -o p000.h5
    \b
    Example (CSV of the naked-eye sky to stdout):
      startrack catalog-filter --mag-max 6 | head
    \b
    Example (Gaia DR3 to G 9 with Hipparcos below Hp 5, Gaia source ids, positions for 2026.9; the extra
    startrack[gaia]):
      startrack catalog-filter --catalog gaia --mag-max 9 --epoch 2026.9 -o deep.h5
    """
    from startrack.catalog import load_catalog, write_catalog
    from startrack.errors import BadInputError
    from startrack.formats.atomic import check_writable

    if mag_min is not None and mag_max is not None and mag_min > mag_max:
        raise BadInputError("--mag-min", None, f"{mag_min:g} is larger than --mag-max {mag_max:g}")
    if output != "-":
        check_writable(output)
    cat = load_catalog(catalog)
    n_in = len(cat)
    cat = cat.filter_magnitude(mag_min, mag_max)
    if epoch is not None:
        cat = cat.propagate(epoch)
    if merge_arcsec is not None:
        cat = cat.merge_close(merge_arcsec)
    if uniform is not None:
        cat = cat.thin_uniform(uniform, cell_deg)
    if len(cat) == 0:
        raise BadInputError("--mag-min/--mag-max", None, "no star is left after filtering")
    write_catalog(cat, output)
    extra = ""
    if merge_arcsec is not None:
        extra += f", {cat.params.get('merged_groups', 0)} close groups merged"
    info(quiet, f"catalog-filter: kept {len(cat)} of {n_in} stars (mag {cat.mag.min():.2f} to {cat.mag.max():.2f}, "
                f"epoch {cat.epoch:g}{extra}) -> {output if output != '-' else 'stdout'}")
