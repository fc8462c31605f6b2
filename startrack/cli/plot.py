"""startrack plot: pictures of frames, tracks, residuals and evaluations."""
import click

from startrack.cli.options import handle_errors, info, input_argument, quiet_option


@click.command("plot", short_help="Pictures: annotated frames, tracking errors, residuals, evaluations.")
@input_argument
@click.option("--kind", type=click.Choice(["image", "residuals", "track", "evaluate"]), default="image",
              show_default=True, help="What to draw.")
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False),
              help="PNG (numbered per frame for image/residuals when several).")
@click.option("--mag-limit", type=float, default=7.0, show_default=True,
              help="image: faintest catalog star drawn as predicted.")
@click.option("--title", default="", help="Chart title.")
@quiet_option
@handle_errors
def command(input, kind, output, mag_limit, title, quiet):
    """Draw what people would rather look at than read.

    \b
    --kind image      each solved frame: detections, identified stars labelled with HIP and
                      proper names, catalog stars predicted from the attitude, a north/east
                      compass and the boresight coordinates (needs image.path)
    --kind residuals  quiver plot of each star's residual after the attitude solve
    --kind track      per-frame cross-boresight and roll error against the truth, by mode
    --kind evaluate   success and time against the condition, from `evaluate --json`

    \b
    Example:
      startrack centroid sky.tiff --camera cam.json | startrack identify -d db.h5 | startrack attitude \\
          | startrack plot --kind image -o sky-solved.png
    """
    import json

    from startrack.errors import BadInputError
    from startrack.formats.frame import read_frames
    from startrack.render import numbered_path

    from startrack.imageio import check_plot_output

    check_plot_output(output)
    if kind == "evaluate":
        from startrack.evaluate import plot_results
        from startrack.formats.frame import read_json_file

        doc = read_json_file(input)
        if "rows" not in doc:
            raise BadInputError(input, "rows", "is missing: give the JSON of `startrack evaluate --json`")
        plot_results(doc["rows"], output, title=title)
        info(quiet, f"plot: {output}")
        return
    from startrack.cli.batch import resolve_image_path
    docs = []
    for rec in read_frames(input):
        if rec.error is not None:
            raise rec.error
        resolve_image_path(rec)
        docs.append(rec.doc)
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
            from startrack.imageio import read_image
            from startrack.plot import annotate_solution

            p = (doc.get("image") or {}).get("path")
            if not p:
                raise BadInputError(input, "image.path", "is missing: --kind image needs the image")
            image, _ = read_image(p)
            annotate_solution(path, image, doc, cat, mag_limit)
        made.append(path)
    if not made:
        click.echo(f"startrack plot: {input}: no frame has an attitude with status ok: no picture written", err=True)
        raise SystemExit(1)
    info(quiet, f"plot: {len(made)} picture(s): {made[0]}" + (f" ... {made[-1]}" if len(made) > 1 else ""))
