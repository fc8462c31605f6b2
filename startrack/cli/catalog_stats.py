"""startrack catalog-stats: how many stars will a sensor see?"""
import click

from startrack.cli.options import (
    CAMERA_EXCLUSIVE,
    Command,
    Int,
    camera_from_options,
    camera_options,
    catalog_option,
    handle_errors,
    mag_options,
    quiet_option,
    seed_option,
)


@click.command("catalog-stats", cls=Command, exclusive=CAMERA_EXCLUSIVE, ordered=[("mag_min", "mag_max")],
               short_help="Monte Carlo count of catalog stars in a sensor's field.")
@catalog_option
@camera_options
@mag_options(max_help="Count only stars at most this faint.", min_help="Count only stars at least this faint.")
@click.option("--count", "-n", "samples", type=Int(1, 10_000_000), default=100000, show_default=True,
              help="Number of random attitudes.")
@seed_option
@click.option("--json", "as_json", is_flag=True, help="Write JSON instead of the text table (a flag, as in every command).")
@quiet_option
@handle_errors
def command(catalog, camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2,
            mag_max, mag_min, samples, seed, as_json, quiet):  # noqa: ARG001 - nothing to hide
    """Count the stars inside a camera's field over random attitudes.

    The Monte Carlo of paper 000 Fig. 2 and paper 003 Fig. 3: uniformly random
    boresights and rolls; the rectangular image (with distortion) decides what
    is in the field.  Prints the minimum, mean and percentiles of the count, the
    fraction of the sky with at least 3, 4, 5 stars, the histogram of the
    brightest star's magnitude and the catalog's stars per magnitude bin.

    \b
    Example (paper 000's sensor: 8 x 8 degrees, Hp <= 6.59):
      startrack catalog-stats --fov-deg 8 --size 480x480 --mag-max 6.59 --seed 1
    \b
    Example (a real lens and sensor, JSON out):
      startrack catalog-stats --focal-length-mm 41.1 --pixel-pitch-um 6 --size 752x480 --mag-max 6.59 --json
    """
    import json

    import numpy as np

    from startrack.catalog import field_statistics, load_catalog
    from startrack.cli.options import require_stdout
    from startrack.errors import BadInputError

    require_stdout()
    # no default size: the stars in a field depend on its shape (issue 41: 1024x1024 was assumed silently)
    cam = camera_from_options(camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2)
    if samples < 1:
        raise BadInputError("--samples", None, f"must be at least 1, got {samples}")
    cat = load_catalog(catalog).filter_magnitude(mag_min, mag_max)
    if len(cat) == 0:
        raise BadInputError("--mag-min/--mag-max", None, "no star is left after filtering")
    rng = np.random.default_rng(seed)
    stats = field_statistics(cat, cam, samples, rng)
    summary = stats.summary()
    fx, fy = cam.fov_deg
    summary["params"].update(catalog=catalog or "shipped", mag_min=mag_min, mag_max=mag_max, seed=seed,
                             camera=cam.to_dict())
    if as_json:
        from startrack._version import __version__

        summary["startrack_version"] = __version__
        click.echo(json.dumps(summary, indent=2))
        return
    lines = [
        f"catalog: {len(cat)} stars (mag {cat.mag.min():.2f} to {cat.mag.max():.2f}); "
        f"camera {cam.width}x{cam.height} px, FOV {fx:.3f} x {fy:.3f} deg (diagonal {cam.diagonal_fov_deg:.3f})",
        f"random attitudes: {samples} (seed {seed})",
        "",
        "stars in the field",
        f"  min {summary['min']}   mean {summary['mean']:.2f}   std {summary['std']:.2f}   max {summary['max']}",
        "  percentiles  " + "  ".join(f"p{k}={v:g}" for k, v in summary["percentiles"].items()),
        "  sky fraction with at least N stars:",
        "    " + "   ".join(f">={k}: {100 * v:6.2f}%" for k, v in summary["fraction_at_least"].items()),
        "",
        "brightest star in the field (magnitude histogram)",
    ]
    h = summary["brightest_mag_histogram"]
    total = max(1, sum(h["counts"]))
    for lo, hi, n in zip(h["edges"][:-1], h["edges"][1:], h["counts"]):
        bar = "#" * int(round(40 * n / total))
        lines.append(f"  {lo:5.1f} .. {hi:5.1f}  {100 * n / samples:6.2f}%  {bar}")
    if summary["brightest_mag_empty_fields"]:
        lines.append(f"  (no star at all in {summary['brightest_mag_empty_fields']} fields)")
    lines += ["", "catalog stars per magnitude bin"]
    edges = summary["mag_bins"]["edges"]
    for lo, hi, n in zip(edges[:-1], edges[1:], summary["mag_bins"]["counts"]):
        lines.append(f"  {lo:5.1f} <= mag < {hi:4.1f}: {n:6d}")
    click.echo("\n".join(lines))
