"""startrack plot: pictures of frames, tracks, residuals and evaluations."""
import click

from startrack.cli.options import Command, handle_errors, info, input_argument, mag_options, quiet_option


@click.command("plot", cls=Command, short_help="Pictures: annotated frames, tracking errors, residuals, evaluations.")
@input_argument
@click.option("--kind", type=click.Choice(["image", "residuals", "track", "evaluate"]), default="image",
              show_default=True, help="What to draw.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False),
              help="The picture: .png, .pdf or .svg (numbered per frame for image/residuals when several).")
@mag_options(max_help="image: faintest catalog star drawn as predicted.", max_default=7.0, with_min=False)
@click.option("--title", default="", help="Chart title.")
@click.option("--constellations", is_flag=True,
              help="image: draw the constellations' stick figures and names (the shipped public-domain table).")
@click.option("--json", "as_json", is_flag=True,
              help="track: also print the plotted statistics (RMS errors per mode, recoveries) as JSON on stdout.")
@quiet_option
@handle_errors
def command(input, kind, output, mag_max, title, constellations, as_json, quiet):
    """Draw what people would rather look at than read.

    \b
    --kind image      each solved frame: detections, identified stars labelled with HIP and
                      proper names, catalog stars predicted from the attitude, a north/east
                      compass and the boresight coordinates (needs image.path); with
                      --constellations the stick figures and names too
    --kind residuals  quiver plot of each star's residual after the attitude solve
    --kind track      per-frame cross-boresight and roll error against the truth, by mode
    --kind evaluate   success and time against the condition, from `evaluate --json`

    \b
    Example (a real photo with a known camera, solved and drawn):
      startrack build-kvector --camera cam.json --mag-max 6.5 -o esa.h5
      startrack centroid sky.tiff --camera cam.json | startrack identify -d esa.h5 | startrack attitude \\
          | startrack plot --kind image -o sky-solved.png
    \b
    Example (the solved photo with the constellations, as a PDF):
      startrack solve sky.tiff > sky.json
      startrack plot sky.json --constellations -o sky-constellations.pdf
    """
    import json

    from startrack.cli.paths import numbered_path
    from startrack.errors import BadInputError
    from startrack.formats.frame import read_frames
    from startrack.imageio import check_plot_output

    check_plot_output(output)
    if constellations and kind != "image":
        raise BadInputError("--constellations", None, f"draws on a frame's picture: only with --kind image, not {kind}")
    if as_json and kind != "track":
        raise BadInputError("--json", None, f"prints the statistics of --kind track, not of {kind}")
    if kind == "evaluate":
        from startrack.formats.frame import read_json_file
        from startrack.plot import plot_results

        doc = read_json_file(input)
        if "rows" not in doc:
            raise BadInputError(input, "rows", "is missing: give the JSON of `startrack evaluate --json`")
        from startrack.evaluate import validate_rows

        plot_results(validate_rows(doc["rows"], input), output, title=title or _evaluate_title(doc))
        info(quiet, f"plot: {output}")
        return
    from startrack.cli.batch import resolve_image_path
    from startrack.formats.frame import read_frame_image, validate_frame

    docs, sources = [], []
    for rec in read_frames(input):
        if rec.error is not None:
            raise rec.error
        # every frame checked where it is read: a bad one is named by its line and field, never an internal error
        doc = rec.doc if isinstance(rec.doc, dict) else {}
        need = ("stars",) if "stars" in doc else ()
        solved = isinstance(doc.get("attitude"), dict) and doc["attitude"].get("status") == "ok"
        if kind == "image" or (kind == "residuals" and solved):
            need += ("camera",)       # what the picture is drawn with (unsolved frames are skipped)
        validate_frame(rec.doc, rec.source, need)
        resolve_image_path(rec)
        docs.append(rec.doc)
        sources.append(rec.source)
    if not docs:
        raise BadInputError(input, None, "holds no frame document")
    if kind == "track":
        from startrack.plot import plot_track_errors

        if not any((d.get("attitude") or {}).get("status") == "ok" for d in docs):
            raise BadInputError(input, "attitude", f"no frame of {len(docs)} has an attitude: nothing to plot "
                                "(give the output of `startrack track`)")
        if not any("truth" in d for d in docs):
            raise BadInputError(input, "truth", "no frame has a truth section: the errors need rendered frames")

        stats = plot_track_errors(docs, output, title)
        if as_json:       # only when asked: the picture is the output (issue 40)
            click.echo(json.dumps(stats, indent=1))
        info(quiet, f"plot: {output}")
        return
    from startrack.catalog import load_catalog

    cat = load_catalog()
    made = []
    for i, doc in enumerate(docs):
        path = numbered_path(output, i, len(docs))
        if kind == "residuals":
            from startrack.plot import plot_residuals

            if (doc.get("attitude") or {}).get("status") != "ok":
                continue
            plot_residuals(doc, path)
        else:
            from startrack.plot import annotate_solution

            image, _ = read_frame_image(doc, sources[i], "--kind image needs the image")
            annotate_solution(path, image, doc, cat, mag_max, constellations=constellations)
        made.append(path)
    if not made:
        click.echo(f"startrack plot: {input}: no frame has an attitude with status ok: no picture written", err=True)
        raise SystemExit(1)
    info(quiet, f"plot: {len(made)} picture(s): {made[0]}" + (f" ... {made[-1]}" if len(made) > 1 else ""))


def _evaluate_title(doc) -> str:
    """The conditions every point of an ``evaluate --json`` document shares: field, size, magnitude limit.

    ``params.mag_max`` (``mag_limit`` in documents written before it was renamed after ``--mag-max``).
    """
    params = doc.get("params") if isinstance(doc.get("params"), dict) else {}
    parts = []
    cam = params.get("camera")
    if isinstance(cam, dict):
        try:
            from startrack.camera import Camera

            c = Camera.from_dict(cam)
            parts.append(f"{c.fov_deg[0]:.1f} x {c.fov_deg[1]:.1f} deg field, {c.width}x{c.height} px")
        except Exception:  # noqa: BLE001 - a title is no reason to refuse the chart
            pass
    mag = params.get("mag_max", params.get("mag_limit"))
    if isinstance(mag, (int, float)):
        parts.append(f"stars to Hp {mag:g}")
    return ", ".join(parts)
