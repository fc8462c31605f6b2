"""startrack track: tracking mode over image sequences."""
import click

from startrack.cli.options import (
    Command,
    FiniteFloat,
    Int,
    NoTimeNotice,
    NumberList,
    RegistryChoice,
    apparent_from_options,
    apparent_options,
    calibration_frame_options,
    calibration_from_options,
    catalog_option,
    handle_errors,
    identify_algorithms,
    load_camera_file,
    mag_options,
    output_option,
    parity_option,
    quiet_option,
    retired_algorithms,
)


@click.command("track", cls=Command, short_help="Track the attitude over an image sequence (predictive windows, fall-back).")
@click.argument("inputs", nargs=-1, metavar="[FRAMES.jsonl | IMAGE...]")
@click.option("--database", "-d", required=True, type=click.Path(dir_okay=False),
              help="k-vector database for the lost-in-space start and fall-backs.")
@click.option("--camera", "camera_file", type=click.Path(dir_okay=False), default=None,
              help="Camera JSON (needed for bare image files).")
@catalog_option
@mag_options(max_help="Faintest catalog star predicted (default: the database's).", with_min=False)
@click.option("--frame-interval-s", type=FiniteFloat(0, 86400, min_open=True), default=None,
              help="Time between frames, used only for frames without image.time (e.g. bare images).")
@click.option("--initial-quaternion", type=NumberList(-1, 1, length=4, unit=True, as_text=True), default=None,
              help="Start from this attitude (q1,q2,q3,q4).")
@click.option("--rate-prior", type=NumberList(-360, 360, length=3, as_text=True), default=None,
              help="Initial body rate wx,wy,wz (deg/s).")
@click.option("--window-px", type=Int(1, 1000), default=8, show_default=True,
              help="Base half-size of the prediction windows.")
@click.option("--sigma-px", type=FiniteFloat(0, 100, min_open=True), default=0.3, show_default=True,
              help="Centroid noise (1 sigma, px) of the windowed centroids in tracking mode (lost-in-space "
                   "acquisition uses each star's own sigma_px, else 0.5, as identify does).")
@click.option("--exposure-ms", type=FiniteFloat(0, 3.6e6, min_open=True), default=None,
              help="Exposure for frames without image.exposure_ms (default 100).")
@click.option("--max-gap-s", type=FiniteFloat(0, min_open=True), default=0.5, show_default=True,
              help="Longer without an attitude (a gap or a blackout) restarts from lost in space.")
@click.option("--algorithm", "-a", type=RegistryChoice(lambda: identify_algorithms("kvector"), retired=retired_algorithms),
              default="pyramid", show_default=True, help="Lost-in-space algorithm.")
@parity_option
@calibration_frame_options
@apparent_options
@output_option()
@click.option("--resume", is_flag=True,
              help="Keep the frames already in the -o file (a run cut short) and track only the rest: the first of "
                   "them is solved lost in space (as after a gap), the times go on from the file's.")
@quiet_option
@handle_errors
def command(inputs, database, camera_file, catalog, mag_max, frame_interval_s, initial_quaternion, rate_prior,
            window_px, sigma_px, exposure_ms, max_gap_s, algorithm, parity, bias, dark, flat, obs_time,
            velocity_km_s, no_aberration, output, resume, quiet):
    """Track the attitude frame by frame: adds `identification`, `attitude` and `track`.

    Input: frame documents naming images (JSON Lines, e.g. from `startrack
    render --frames N`, whose image.time and image.exposure_ms it reads), in
    time order, or image files with --camera and --frame-interval-s.  Each
    output frame has a `track` section: mode (tracking, single-star,
    lost-in-space, lost), predicted vs measured positions, the filtered rate
    and its sigma (deg/s), the rate from the streaks, the window size and the
    time per frame.  Stars of a turning camera are fitted as streaks (position
    at mid-exposure).  The first frame, and any frame after a gap or blackout
    longer than --max-gap-s, is solved lost in space with identify's search.
    Catalog positions are moved to the first frame's image.time (proper motion)
    and, every frame, to their apparent places (stellar aberration for the
    Earth's velocity at the frame's time plus the camera's own,
    observer.velocity_km_s or --velocity-km-s): the attitude is the camera's
    true orientation in ICRS (attitude.apparent records the setting).
    Out-of-order time stamps are refused.  Exit status 1 when any frame has no
    attitude.

    \b
    Example (a rendered sequence, then tracking):
      startrack build-kvector --fov-deg 12 --size 1024x768 --mag-max 6.5 -o db12.h5
      startrack render --fov-deg 12 --size 1024x768 --frames 30 --rate-deg-s 0.3,-0.2,0.5 \\
          --frame-interval-s 0.1 --seed 1 -o seq/frame.png > seq.jsonl
      startrack track --database db12.h5 < seq.jsonl | jq -c '[.track.mode, .attitude.ra, .attitude.dec]'
    """

    import numpy as np

    from startrack.apparent import frame_apparent
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.cli.batch import run_frames
    from startrack.errors import BadInputError
    from startrack.formats.frame import FRAME_FORMAT, read_frame_image
    from startrack.kvector import check_database, load_kvector
    from startrack.rotations import normalize_quaternion, quaternion_to_dcm
    from startrack.timeutil import julian_year, parse_time
    from startrack.track import MODES, Tracker, TrackerConfig

    calibration = calibration_from_options(bias, dark, flat)
    apparent = apparent_from_options(obs_time, velocity_km_s, no_aberration)
    no_time = NoTimeNotice("track")

    db = load_kvector(database)
    cam_override = None
    if camera_file:
        cam_override = load_camera_file(camera_file)
    init = None
    if initial_quaternion:
        q = np.array([float(v) for v in initial_quaternion.split(",")])
        if len(q) != 4 or not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1) > 1e-6:
            raise BadInputError("--initial-quaternion", None, "must be a unit quaternion q1,q2,q3,q4")
        init = quaternion_to_dcm(normalize_quaternion(q))
    rate = None
    if rate_prior:
        rate = np.radians([float(v) for v in rate_prior.split(",")])
        if len(rate) != 3:
            raise BadInputError("--rate-prior", None, "expected wx,wy,wz in deg/s")
    cat = load_catalog(catalog)
    config = TrackerConfig(mag_limit=mag_max if mag_max is not None else float(db.star_mag.max()),
                           window_px=window_px, sigma_px=sigma_px, max_gap_s=max_gap_s,
                           exposure_s=(exposure_ms if exposure_ms is not None else 100.0) / 1000, algorithm=algorithm)
    state = {"tracker": None, "t0": None, "t_prev": None, "modes": {m: 0 for m in MODES}}
    if resume and output != "-":
        state["t0"], state["t_prev"] = _resumed_times(output, parse_time)

    # Bare image files become minimal frame documents.
    names = list(inputs) or ["-"]
    if all(not (n == "-" or n.lower().endswith((".json", ".jsonl", ".ndjson"))) for n in names):
        if cam_override is None:
            raise BadInputError("--camera", None, "is needed with image files")
        if frame_interval_s is None:
            raise BadInputError("--frame-interval-s", None, "is needed with image files (they carry no time)")
        import json
        import tempfile

        tmp = tempfile.NamedTemporaryFile("w", suffix=".jsonl", delete=False)
        for n in names:
            tmp.write(json.dumps({"format": FRAME_FORMAT, "image": {"path": n}}) + "\n")
        tmp.close()
        source = tmp.name
    elif len(names) == 1:
        source = names[0]
    else:
        raise BadInputError("INPUT", None, "give one frame-document stream, or image files")

    def process(doc, src, index, total):  # noqa: ARG001 - the batch callback's signature
        cam = cam_override if cam_override is not None else (
            Camera.from_dict(doc["camera"], src) if "camera" in doc else None)
        if cam is None:
            raise BadInputError(src, "camera", "is missing (give --camera)")
        setting = frame_apparent(doc, apparent, src)
        if state["tracker"] is None:
            check_database(db, cam)
            stars = cat
            if setting.time.known:
                # Catalog positions at the sequence's epoch (proper motion), as render placed them.
                stars = cat.propagate(julian_year(setting.time.time))
            state["tracker"] = Tracker(stars, cam, db, config, init, rate, parity=parity)
        tracker = state["tracker"]
        if setting.state is not None or tracker.vectors is not tracker.astrometric:
            tracker.set_directions(setting.apparent(tracker.astrometric, tracker.catalog.plx))
        image, meta = read_frame_image(doc, src, "tracking needs the images")
        path = doc["image"]["path"]
        saturation = meta["saturation"]
        if calibration is not None:
            image, saturation = calibration.apply(image, saturation, path)
        image_doc = doc.get("image") or {}
        tstr = image_doc.get("time")
        if tstr:
            t_abs = parse_time(tstr, f"{src}: image.time")
            if state["t0"] is None:
                state["t0"] = t_abs
            t = (t_abs - state["t0"]).total_seconds()
        elif frame_interval_s:
            # A gap in the time stamps: one frame interval after the previous frame.
            t = 0.0 if state["t_prev"] is None else state["t_prev"] + frame_interval_s
        else:
            raise BadInputError(src, "image.time", "is missing (give --frame-interval-s)")
        exp_ms = image_doc.get("exposure_ms")
        if exp_ms is not None and (isinstance(exp_ms, bool) or not isinstance(exp_ms, (int, float))
                                   or not 0 < exp_ms <= 3.6e6):
            raise BadInputError(src, "image.exposure_ms", f"must be a positive number of ms up to an hour, got "
                                                          f"{exp_ms!r}"[:160])
        exposure_s = exp_ms / 1000.0 if exp_ms is not None else config.exposure_s
        doc["image"] = {**(doc.get("image") or {}), "width": image.shape[1], "height": image.shape[0]}
        if calibration is not None:
            doc["image"]["calibration"] = calibration.record()
        doc["camera"] = cam.to_dict()
        no_time(setting.aberration)      # after the frame's input was found usable
        out = state["tracker"].step(image, t, saturation, exposure_s)
        state["t_prev"] = t
        state["modes"][out["track"]["mode"]] += 1
        doc["stars"] = out["stars"]
        doc["identification"] = out["identification"]
        doc["attitude"] = out["attitude"]
        if isinstance(doc["attitude"], dict):
            doc["attitude"]["apparent"] = setting.record()
        doc["track"] = out["track"]
        return doc

    tally = run_frames(source, output, "attitude", process, quiet, "track", finish=False, resume=resume)
    modes = state["modes"]
    n = sum(modes.values())
    with_att = n - modes["lost"]
    if not quiet or modes["lost"]:
        click.echo(f"track: {with_att} of {n} frame(s) with an attitude ("
                    + ", ".join(f"{modes[m]} {m}" for m in MODES if m != "lost") + f"), {modes['lost']} lost"
                    + (f"; {tally.skipped} already in the output (--resume)" if tally.skipped else ""), err=True)
    if tally.bad:
        click.echo(f"track: {tally.bad} frame(s) with bad input", err=True)
    if tally.exit_code or modes["lost"]:
        raise SystemExit(tally.exit_code or 1)


def _resumed_times(output, parse_time):
    """``(t0, t_prev)`` of the sequence already in ``output`` (``--resume``): the first frame's time (its
    image.time less its track.t_s) and the last frame's track.t_s, so that a resumed run's times go on from them."""
    import datetime
    import json
    import os

    t0 = t_prev = None
    if not os.path.exists(output):
        return t0, t_prev
    with open(output, "rb") as fh:
        for raw in fh:
            if not raw.endswith(b"\n"):
                break
            try:
                doc = json.loads(raw)
                t_s = float(doc["track"]["t_s"])
            except (ValueError, KeyError, TypeError):
                continue     # the batch runner's own resume check names a document that is not this command's
            if t0 is None and isinstance((doc.get("image") or {}).get("time"), str):
                t0 = parse_time(doc["image"]["time"], f"{output}: image.time") - datetime.timedelta(seconds=t_s)
            t_prev = t_s
    return t0, t_prev
