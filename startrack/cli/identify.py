"""startrack identify: lost-in-space star identification of frame documents."""
import click

from startrack.cli.options import (
    Command,
    FiniteFloat,
    Int,
    NoTimeNotice,
    RegistryChoice,
    apparent_from_options,
    apparent_options,
    catalog_option,
    handle_errors,
    identify_algorithms,
    input_argument,
    jobs_option,
    load_camera_file,
    output_option,
    parity_option,
    quiet_option,
    resume_option,
    retired_algorithms,
    sigma_px_option,
)


def _algorithm_options(func):
    """One option per configuration field of the registered algorithms (``--max-triads``, ``--gamma-mag``, ...)."""
    from startrack.identify import config_fields

    for f in reversed(config_fields()):
        kind = f["type"] if f["type"] in (int, float, bool, str) else float
        flag = "--" + f["name"].replace("_", "-")
        default = "" if f["default"] is None else f" (default {f['default']})"
        text = f"{f['help']}{default} [{', '.join(f['algorithms'])}]"
        if kind is bool:
            func = click.option(flag + "/--no-" + f["name"].replace("_", "-"), f["name"], default=None,
                                help=text)(func)
        else:
            func = click.option(flag, f["name"], type=kind, default=None, help=text)(func)
    return func


def algorithm_settings(kwargs, algorithm):
    """The chosen algorithm's configuration from the generated options; another algorithm's option is an error."""
    from startrack.errors import BadInputError
    from startrack.identify import config_fields, make_config

    values = {}
    for f in config_fields():
        v = kwargs.pop(f["name"], None)
        if v is None:
            continue
        if algorithm not in f["algorithms"]:
            flag = "--" + f["name"].replace("_", "-")
            raise BadInputError(flag, None, f"is a setting of {', '.join(f['algorithms'])}, not of {algorithm}")
        values[f["name"]] = v
    return make_config(algorithm, values)


def _algorithm_choice():
    from startrack.identify import algorithm_names

    return click.Choice(algorithm_names())


@click.command("identify", cls=Command, short_help="Identify the stars of frame documents (lost in space).")
@input_argument
@click.option("--database", "-d", required=True, type=click.Path(dir_okay=False),
              help="Database from build-kvector (or build-labels for --algorithm labelling).")
@click.option("--algorithm", "-a", type=RegistryChoice(identify_algorithms, retired=retired_algorithms),
              default="pyramid", show_default=True,
              help="Identification algorithm (a registered name; labelling takes a build-labels database, "
                   "modified-pyramid a build-triangles one, the others build-kvector's).")
@click.option("--camera", "camera_file", type=click.Path(dir_okay=False), default=None,
              help="Camera JSON, for frames without a camera section (or to override it).")
@sigma_px_option()
@click.option("--tolerance-arcsec", type=FiniteFloat(0, 600, min_open=True), default=None,
              help="Inter-star angle tolerance (arcsec), overriding the one derived from --sigma-px.")
@click.option("--max-stars", type=Int(3, 1000), default=20, show_default=True,
              help="Brightest stars the pattern search uses (all are matched at the end).")
@click.option("--max-search-stars", type=Int(3, 100000), default=80, show_default=True,
              help="When the search of the --max-stars brightest finds nothing, search again with twice as many, "
                   "up to this many (a field whose brightest detections are not catalog stars); "
                   "--max-search-stars equal to --max-stars: one search.")
@click.option("--max-false-probability", type=FiniteFloat(0, 1, min_open=True), default=1e-6, show_default=True,
              help="Refuse an identification more likely than this to be a coincidence.")
@click.option("--max-proposals", type=int, default=200, show_default=True,
              help="Search budget: proposals verified before giving up (each deeper search of --max-search-stars "
                   "has its own).")
@click.option("--max-time-ms", type=float, default=2000.0, show_default=True,
              help="Search budget: milliseconds per frame before giving up.")
@catalog_option
@click.option("--match-all/--database-only", default=True, show_default=True,
              help="After the attitude, match the detections the database lacks to the catalog (--catalog).")
@_algorithm_options
@click.option("--calibration-frames", type=Int(0, 100000), default=10, show_default=True,
              help="brightness: each identified frame's brightest star measures Eq. 9's In_k; the next frames are "
                   "searched with the mean of the last N such frames (--brightness-calibration is the start; "
                   "0: every frame uses only --brightness-calibration). Frames then run in order (no --jobs).")
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="Annotated PNG of each frame with an image (numbered when several).")
@parity_option
@apparent_options
@output_option()
@click.option("--max-frame-stars", type=Int(3, 10_000_000), default=10_000, show_default=True,
              help="Detections read per frame: the brightest this many (the stars are brightest first); a frame "
                   "with more is identified on them, says so on stderr and records stars_read.")
@jobs_option
@resume_option
@quiet_option
@handle_errors
def command(input, database, algorithm, camera_file, sigma_px, tolerance_arcsec, max_stars, max_search_stars,
            max_false_probability, max_proposals, max_time_ms, catalog, match_all, calibration_frames, plot, parity,
            obs_time, velocity_km_s, no_aberration, max_frame_stars, output, jobs, resume, quiet, **settings):
    """Identify the stars of each frame: adds an `identification` section.

    Reads frame documents with `stars` (x, y, brightest first) and a `camera`,
    from a file or stdin; writes `identification` with status, algorithm,
    matches (star index -> HIP id), time_ms, trials (proposals verified) and
    false_match_probability, the probability that the match is a coincidence,
    and parity (a mirrored star list is identified too: --parity).
    With the frame's time (image.time or --time) the final catalog match and
    quaternion_estimate use the stars' apparent places (stellar aberration
    for the Earth's velocity plus --velocity-km-s or observer.velocity_km_s),
    recorded in identification.apparent, as attitude does.
    The algorithm proposes star patterns in its paper's order; each is verified
    (attitude, every detection matched within its own sigma) until one passes
    the false-match limit or the search budget runs out.  A frame that cannot
    be identified gets status "failed" and a reason; the batch goes on.  The
    database is loaded once (its time is reported on stderr, not in time_ms).
    Each algorithm's own settings are options below, marked with the
    algorithms that take them.

    \b
    Example (build a database once, then identify a stream):
      startrack build-kvector --fov-deg 20 --mag-max 5.0 -o db.h5
      startrack render --stars-only --count 100 --fov-deg 20 --mag-max 5 --sigma-px 0.3 --seed 1 \\
          | startrack identify --database db.h5 --algorithm pyramid -o ids.jsonl \\
          || echo "exit status $?: some frames were not identified (too few stars)"
      jq -c .identification.status ids.jsonl | sort | uniq -c
    \b
    Example (a real photo: the database is built for its camera, 11.4 x 8.6 deg):
      startrack build-kvector --camera cam.json --mag-max 6.5 -o esa.h5
      startrack centroid sky.tiff --camera cam.json | startrack identify -d esa.h5 --plot sky-id.png > sky-id.json
    """
    import os
    import time

    from startrack.camera import Camera
    from startrack.cli.batch import StreamNames, run_frames
    from startrack.cli.options import info
    from startrack.errors import BadInputError
    from startrack.formats.sections import to_section
    from startrack.identify import (
        IdentifyParams,
        database_kind,
        warm_up,
    )
    from startrack.parity import identify_either_parity

    config = algorithm_settings(settings, algorithm)
    from startrack.apparent import frame_apparent

    apparent = apparent_from_options(obs_time, velocity_km_s, no_aberration)
    no_time = NoTimeNotice("identify")
    from startrack.identify.calibration import CalibrationCarry, carries_calibration

    carry = None
    if calibration_frames > 0 and carries_calibration(config):
        carry = CalibrationCarry(config.brightness_calibration, calibration_frames)
        if jobs > 1:
            # Each frame's calibration comes from the frames before it: they are identified in order.
            info(quiet, f"identify: {algorithm} carries its calibration frame to frame: frames run in order "
                        "(--jobs ignored; --calibration-frames 0 to run them in parallel)")
            jobs = 1
    if max_stars < 3:
        raise BadInputError("--max-stars", None, f"must be at least 3, got {max_stars}")
    if max_proposals < 1:
        raise BadInputError("--max-proposals", None, f"must be at least 1, got {max_proposals}")
    if not max_time_ms > 0:
        raise BadInputError("--max-time-ms", None, f"must be positive, got {max_time_ms}")
    kind = database_kind(algorithm)
    t_load = time.perf_counter()
    db = _load_database(database, kind)
    deep = None
    if match_all:
        from startrack.catalog import load_catalog
        from startrack.identify.catalog_match import CatalogStars, CatalogStarsAt

        base = load_catalog(catalog)
        deep = CatalogStars.from_catalog(base)
        at_epoch = {}

        def deep_at(t):
            """The catalog at the frame's time (proper motion), to 0.001 yr (8.8 h; 0.01" for the fastest
            stars), one epoch kept: the final match compares with where the stars are (CatalogStarsAt: the stars
            a frame reads moved, not the whole catalog)."""
            from startrack.timeutil import julian_year

            ep = round(julian_year(t), 3)
            if abs(ep - base.epoch) < 1e-9 and abs(((getattr(db, "params", None) or {}).get("epoch", ep)) - ep) < 1e-9:
                return deep
            if ep not in at_epoch:
                at_epoch.clear()
                # The database's stars move by their catalog stars' motion since the database's epoch.
                db_epoch = (getattr(db, "params", None) or {}).get("epoch", base.epoch)
                at_epoch[ep] = CatalogStarsAt(deep, base, ep, None if abs(db_epoch - base.epoch) < 1e-9 else db_epoch)
            return at_epoch[ep]
    override = None
    if camera_file:
        override = load_camera_file(camera_file)
    params_for_warm_up = IdentifyParams(max_time_ms=max_time_ms)
    warm_up(algorithm, db, params_for_warm_up, override)
    load_ms = (time.perf_counter() - t_load) * 1000
    params = IdentifyParams(sigma_px=sigma_px, tolerance_arcsec=tolerance_arcsec, max_stars=max_stars,
                            max_search_stars=max_search_stars, max_false_probability=max_false_probability,
                            max_proposals=max_proposals, max_time_ms=max_time_ms)
    checked = {}
    from startrack.imageio import check_plot_output

    check_plot_output(plot)
    plot_names = StreamNames(plot)

    def process(doc, source, index, total):  # noqa: ARG001 - the caller's signature
        if override is not None:
            cam = override
            doc["camera"] = cam.to_dict()
        else:
            if "camera" not in doc:
                raise BadInputError(source, "camera", "is missing (give --camera camera.json)")
            cam = Camera.from_dict(doc["camera"], source)
        key = (cam.width, cam.height, cam.focal_length_px, cam.lens_terms)
        if key not in checked:
            checked[key] = _check(db, cam, kind)
        from startrack.formats.frame import validate_stars

        stars = doc.get("stars")
        if isinstance(stars, list) and len(stars) > max_frame_stars:
            # Memory and time bounded per frame (issue 41: 100,000 stars took 895 MB and 25 s): the brightest
            # detections, which come first, are the ones any identification uses; the rest pass through.
            info(False, f"identify: {source}: {len(stars)} stars, identified on the {max_frame_stars} brightest "
                        "(--max-frame-stars)")
            stars = stars[:max_frame_stars]
        validate_stars({"stars": stars}, source)
        setting = frame_apparent(doc, apparent, source)
        no_time(setting.aberration)
        frame_deep = deep_at(setting.time.time) if deep is not None and setting.time.known else deep
        places = setting.apparent if setting.state is not None else None
        if carry is None:
            result, _ = identify_either_parity(stars, cam, db, algorithm, params, config, frame_deep, parity, places)
        else:
            frame_config, used = carry.config_for(config)
            result, _ = identify_either_parity(stars, cam, db, algorithm, params, frame_config, frame_deep, parity,
                                               places)
            result.details.update(used)
            carry.update(result, index)
        if stars is not doc.get("stars"):
            result.details["stars_read"] = len(stars)
        doc["identification"] = to_section(result)
        if result.status == "ok":
            doc["identification"]["apparent"] = setting.record()
        if plot and (doc.get("image") or {}).get("path") and os.path.exists(doc["image"]["path"]):
            _plot(plot_names(index), doc, db, cam, result)
        return doc

    run_frames(input, output, "identification", process, quiet, "identify", jobs=jobs, resume=resume)
    # Loading is set-up, not identification: reported apart from every frame's time_ms.
    info(quiet, f"identify: database {database} loaded (and kernels readied) in {load_ms:.0f} ms, not in time_ms")


def _load_database(path, kind):
    if kind == "labels":
        from startrack.labels import load_labels

        return load_labels(path)
    if kind == "triangles":
        from startrack.triangles import load_triangles

        return load_triangles(path)
    from startrack.kvector import load_kvector

    return load_kvector(path)


def _check(db, camera, kind):
    if kind == "labels":
        from startrack.labels import check_labels

        check_labels(db, camera)
    elif kind == "triangles":
        from startrack.triangles import check_triangles

        check_triangles(db, camera)
    else:
        from startrack.kvector import check_database

        check_database(db, camera)
    return True


def _plot(path, doc, db, camera, result):
    from startrack.imageio import read_image
    from startrack.names import star_label
    from startrack.plot import annotate_stars

    image, _ = read_image(doc["image"]["path"])
    from startrack.rotations import quaternion_to_dcm

    labels = {m.star: star_label(m.id) for m in result.matches}
    predicted = []
    if result.quaternion_estimate is not None:
        cam_vec = db.star_vector @ quaternion_to_dcm(result.quaternion_estimate).T
        front = cam_vec[:, 2] > 0
        x, y = camera.vectors_to_pixels(cam_vec[front])
        if doc["identification"].get("parity") == "mirrored":
            x = 2.0 * camera.cx - x             # the stars are the camera's flipped (startrack.parity)
        inside = camera.in_image(x, y)
        predicted = list(zip(x[inside], y[inside]))
    title = f"{result.algorithm}: {result.status}, {len(result.matches)} stars identified"
    annotate_stars(path, image, doc["stars"], None, labels,
                   predicted, title)
