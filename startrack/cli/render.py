"""startrack render: synthetic star images, star lists, Monte Carlo sets and sequences."""
import click

from startrack.cli.options import (
    CAMERA_EXCLUSIVE,
    Command,
    FiniteFloat,
    Int,
    NumberList,
    OutputPath,
    camera_from_options,
    camera_options,
    catalog_option,
    handle_errors,
    info,
    mag_options,
    quiet_option,
    seed_option,
)


class _ImagePath:
    """Picklable ``index -> file name`` of a batch's images (numbered as the serial run numbers them)."""

    def __init__(self, output, total):
        self.output, self.total = output, total

    def __call__(self, index):
        from startrack.cli.paths import numbered_path

        return numbered_path(self.output, index, self.total)


def _write_images(items, preview=None):
    """The frame documents of ``(doc, image, path)`` items, their images written (and with ``preview``,
    an ``index -> path`` such as :class:`_ImagePath`, an 8-bit stretched PNG of each for people to look at)."""
    from startrack.imageio import write_image

    for doc, image, path in items:
        if image is not None and path:
            write_image(path, image, header={"STVER": doc["render"]["startrack_version"],
                                             "FRSEED": str(doc["render"]["frame_seed"])})
        if image is not None and preview is not None:
            from startrack.plot import write_preview

            write_preview(preview(int(doc["render"]["frame_index"])), image)
        yield doc


def _render_chunk(task):
    """Dask task: render one chunk of a Monte Carlo set; images written here, documents returned."""
    run, preview = task
    return list(_write_images(run.frames_iter(), preview))


def _floats(text, name, n):
    from startrack.errors import BadInputError

    try:
        values = [float(v) for v in str(text).split(",")]
    except ValueError:
        raise BadInputError(name, None, f"expected {n} comma-separated numbers, got {text!r}") from None
    if len(values) != n:
        raise BadInputError(name, None, f"expected {n} comma-separated numbers, got {len(values)}")
    return values


@click.command("render", cls=Command,
               exclusive=CAMERA_EXCLUSIVE + (("sigma_px", "sigma_arcsec"), ("quaternion", "ra"), ("quaternion", "dec")), short_help="Render star images or star lists with known truth.")
@catalog_option
@camera_options(fisheye=True)
@click.option("--quaternion", type=NumberList(-1, 1, length=4, unit=True, as_text=True), default=None, help="Attitude q1,q2,q3,q4 (scalar last, ICRS to camera).")
@click.option("--ra", type=FiniteFloat(-360, 360), default=None, help="Boresight right ascension, degrees.")
@click.option("--dec", type=FiniteFloat(-90, 90), default=None, help="Boresight declination, degrees.")
@click.option("--roll", type=FiniteFloat(-360, 360), default=0.0, show_default=True, help="Roll (image up, degrees east of north).")
@click.option("--output", "-o", type=click.Path(dir_okay=False), default=None,
              help="Image file (.png, .tif/.tiff, .fits); numbered (sky-0000.png) for several frames.")
@click.option("--documents", type=click.Path(dir_okay=False, allow_dash=True), default="-", show_default=True,
              help="Where the frame documents (JSON Lines) go.")
@click.option("--preview", type=OutputPath(dir_okay=False), default=None,
              help="Also an 8-bit PNG of each image, stretched for people to look at (the -o image keeps the "
                   "sensor's bit depth for the pipeline, and a 16-bit PNG looks black in most viewers); numbered "
                   "like -o for several frames.")
@mag_options(max_help="Faintest magnitude rendered (default: the sensor's 5-sigma detection limit).", with_min=False)
@click.option("--zero-point", "zero_point", type=FiniteFloat(0, min_open=True), default=2.0e6, show_default=True,
              help="Photo-electrons per second from a magnitude-0 star (aperture, optics, QE folded in).")
@click.option("--exposure-ms", type=FiniteFloat(0, 3.6e6, min_open=True), default=100.0, show_default=True, help="Exposure time.")
@click.option("--psf-sigma-px", type=FiniteFloat(0.1, 50), default=1.0, show_default=True, help="Gaussian PSF sigma (defocus).")
@click.option("--full-well-e", type=FiniteFloat(0, min_open=True), default=20000.0, show_default=True, help="Full-well capacity.")
@click.option("--bit-depth", type=click.Choice(["8", "12", "16"]), default="16", show_default=True)
@click.option("--gain-e-per-dn", type=FiniteFloat(0, min_open=True), default=None, help="Gain (default: full well / ADC range).")
@click.option("--bias-dn", type=FiniteFloat(0), default=None, help="Bias level (default: 2% of the ADC range).")
@click.option("--read-noise-e", type=FiniteFloat(0), default=5.0, show_default=True)
@click.option("--dark-current-e-per-s", type=FiniteFloat(0), default=20.0, show_default=True)
@click.option("--background-e-per-s", type=FiniteFloat(0), default=50.0, show_default=True, help="Sky background per pixel.")
@click.option("--prnu", type=FiniteFloat(0, 1), default=0.0, show_default=True, help="Pixel response non-uniformity (1 sigma, fraction).")
@click.option("--hot-pixels", type=Int(0, 10_000_000), default=0, show_default=True,
              help="The sensor's hot pixels: single pixels of 1-200 % of the full well (some saturated), the same "
                   "in every frame of a size (a dark frame rendered alike holds them).")
@click.option("--cosmic-rays", type=Int(0, 10_000_000), default=0, show_default=True,
              help="Cosmic-ray hits: sharp tracks of 1 to 30 pixels.")
@click.option("--dark-subtracted", is_flag=True,
              help="Write the frame as a dark-subtracted one: bias and expected dark current removed, clipped at 0 "
                   "(with --bit-depth 8 and a small sky, most of the background is 0 to a few DN).")
@click.option("--vignetting", type=FiniteFloat(0, 1, min_open=True), default=1.0, show_default=True,
              help="Optics' response at the image corners relative to the centre (cos^4 law; a flat-field pattern).")
@click.option("--gradient", type=FiniteFloat(1, 1e6), default=1.0, show_default=True,
              help="Linear sky gradient in a random direction: brightest / faintest sky across the frame.")
@click.option("--nebulosity-e-per-s", type=FiniteFloat(0), default=0.0, show_default=True,
              help="Peak of smooth nebular emission (clouds, filaments, 1/f structure), e-/s per pixel.")
@click.option("--foreground", type=click.Choice(["disc", "edge", "branches"]), default=None,
              help="An opaque foreground body: a bright disc (a moon), a horizon/roof edge, or tree branches; "
                   "stars behind it are hidden (truth.foreground.hidden_star_ids).")
@click.option("--foreground-fraction", type=FiniteFloat(0, 1, min_open=True, max_open=True), default=0.3,
              show_default=True, help="Fraction of the frame the foreground body covers.")
@click.option("--foreground-e-per-s", type=FiniteFloat(0), default=None,
              help="Foreground surface brightness, e-/s per pixel (default: a disc twice the full well per "
                   "exposure, saturated like a moon; an edge or branches dark).")
@click.option("--horizon", type=click.Choice(["flat", "random"]), default=None,
              help="The ground around a zenith-pointing camera: dark, hiding the sky and the stars below its skyline "
                   "(flat: the astronomical horizon; random: buildings, trees and a ridge drawn from --seed). A "
                   "fisheye camera always has at least the flat one (nothing is drawn beyond 90 deg off-axis).")
@click.option("--extinction-mag", type=FiniteFloat(0, 10), default=0.0, show_default=True,
              help="Atmospheric extinction, magnitudes per air mass (V band: about 0.2), the boresight at the zenith.")
@click.option("--ground-lights", type=Int(0, 10_000), default=0, show_default=True,
              help="Point lights (lamps, lit windows) on the ground below the skyline, as bright as magnitude 0-4 "
                   "stars (with --horizon or a fisheye).")
@click.option("--mirror", type=click.Choice(["x", "y"]), default=None,
              help="Write the image (or star list) mirrored: columns (x) or rows (y) flipped; truth in the written "
                   "pixels, the attitude the un-mirrored camera's.")
@click.option("--no-noise", is_flag=True, help="Expected values only: no shot, dark or read noise.")
@click.option("--mag-noise", type=FiniteFloat(0, 10), default=0.0, show_default=True, help="Magnitude noise, 1 sigma (paper 003: 0.2).")
@click.option("--false-stars", type=Int(0, 100_000), default=0, show_default=True, help="False stars of random position and brightness.")
@click.option("--focal-error-pct", type=FiniteFloat(-50, 50), default=0.0, show_default=True,
              help="Render with f*(1+e/100) while the camera section keeps the nominal f.")
@click.option("--rate-deg-s", type=NumberList(-360, 360, length=3, as_text=True), default="0,0,0", show_default=True,
              help="Angular rate wx,wy,wz in the camera frame (smear, and the turn between frames).")
@click.option("--frames", type=Int(1, 10_000_000), default=1, show_default=True, help="Frames in a sequence.")
@click.option("--frame-interval-s", type=FiniteFloat(0, 86400, min_open=True), default=0.1, show_default=True, help="Time between frames.")
@click.option("--time", "start_time", type=str, default=None,
              help="ISO-8601 time of the (first) frame; proper motion is applied to that epoch. "
                   "Default: the catalog's epoch. Every frame's image.time is written.")
@click.option("--velocity-km-s", type=NumberList(-3000, 3000, length=3, as_text=True), default=None,
              help="The camera's velocity VX,VY,VZ (km/s, GCRS), written to each frame's observer.velocity_km_s and "
                   "added to the Earth's for the aberration rendered.")
@click.option("--orbit-period-s", type=FiniteFloat(0, 1e9, min_open=True), default=None,
              help="With --velocity-km-s: the velocity turns about (v x z) once in this period (a circular orbit).")
@click.option("--no-aberration", is_flag=True,
              help="Render the catalog directions as a camera at rest sees them (default: stellar aberration for "
                   "the Earth's velocity at each frame's time plus --velocity-km-s, and solar light deflection).")
@click.option("--blackout", type=str, default=None,
              help="START:COUNT: frames of a sequence rendered without stars (covered or blinded), e.g. 50:10.")
@click.option("--stars-only", is_flag=True, help="No image: stars straight from the truth, with noise.")
@click.option("--sigma-px", type=FiniteFloat(0, 100), default=None,
              help="Star-list centroid noise added, pixels (1 sigma per axis; default 0).")
@click.option("--sigma-arcsec", type=FiniteFloat(0, 3600), default=None, help="Star-list centroid noise, arcsec (1 sigma per axis).")
@click.option("--max-stars", type=Int(1, 100_000), default=None, help="Star list: keep the N brightest.")
@click.option("--drop-fraction", type=FiniteFloat(0, 1, max_open=True), default=0.0, show_default=True, help="Star list: fraction of stars dropped.")
@click.option("--count", "-n", type=Int(1, 100_000_000), default=1, show_default=True,
              help="Number of random-attitude frames (or sequences).")
@seed_option
@click.option("--jobs", "-j", type=Int(1, 1024), default=1, show_default=True,
              help="With --scheduler: worker processes of a local cluster.")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Render a large --count on a Dask cluster ('local', or tcp://HOST:8786): chunks of frames per "
                   "task, images written by the workers (a shared filesystem), documents in order.")
@click.option("--frame-seed", type=Int(0, 2**63 - 1), default=None, help="Re-render exactly one frame from its recorded frame_seed.")
@click.option("--resume", is_flag=True,
              help="Go on with a --count set cut short: keep the whole sequences already in --documents FILE "
                   "(written by this command with the same options and --seed) and render only the rest.")
@quiet_option
@handle_errors
def command(catalog, camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2, projection, k3, k4,
            quaternion, ra, dec, roll,
            output, documents, preview, mag_max, zero_point, exposure_ms, psf_sigma_px, full_well_e, bit_depth,
            gain_e_per_dn,
            bias_dn, read_noise_e, dark_current_e_per_s, background_e_per_s, prnu, hot_pixels, cosmic_rays,
            dark_subtracted, vignetting, gradient, nebulosity_e_per_s, foreground, foreground_fraction,
            foreground_e_per_s, horizon, extinction_mag, ground_lights, mirror, no_noise, mag_noise,
            false_stars, focal_error_pct, rate_deg_s, frames, frame_interval_s, start_time, velocity_km_s,
            orbit_period_s, no_aberration, blackout, stars_only, sigma_px,
            sigma_arcsec, max_stars, drop_fraction, count, seed, jobs, scheduler, frame_seed, resume, quiet):
    """Render star images (or star lists) of a catalog seen by a camera.

    The image goes to --output (format by extension: 8/16-bit PNG, 16-bit TIFF
    not compressed, FITS) and one frame document per frame (image, camera, truth, render
    parameters) to stdout.  Photometry follows paper 003 Eqs. 7-9, the PSF is a
    Gaussian integrated over each pixel (Eqs. 4-5), and the sensor adds shot,
    dark, read and background noise.  Every random choice follows --seed; each
    document records its frame_seed, which --frame-seed re-renders alone.
    The stars are where a moving camera sees them: proper motion to the
    frame's time, solar light deflection and stellar aberration for the
    Earth's velocity at that time plus --velocity-km-s (--no-aberration: a
    camera at rest); truth is the camera's true attitude.

    \b
    Example (Orion, 20 deg, 1024 x 1024, 16-bit PNG):
      startrack render --fov-deg 20 --size 1024x1024 --ra 83.8 --dec -1.2 -o orion.png > orion.json
    \b
    Example (a Monte Carlo set of 1000 star lists, paper 003's conditions):
      startrack render --stars-only --count 1000 --fov-deg 20 --size 1024x1024 --mag-max 5 \\
          --sigma-arcsec 1.67 --mag-noise 0.2 --max-stars 10 --seed 1 > set.jsonl
    \b
    Example (a tracking sequence: 20 frames at 0.5 deg/s with smear):
      startrack render --fov-deg 12 --size 1024x768 --frames 20 --rate-deg-s 0.3,0.4,0 \\
          --frame-interval-s 0.1 --seed 2 -o seq/frame.png > seq.jsonl
    \b
    Example (a real camera's nuisances: 8-bit dark-subtracted, hot pixels, a tree, mirrored):
      startrack render --fov-deg 10 --size 640x480 --bit-depth 8 --gain-e-per-dn 2 --dark-subtracted \\
          --hot-pixels 50 --foreground branches --foreground-fraction 0.3 --mirror x --seed 4 -o tree.png > tree.json
    \b
    Example (an all-sky camera: equidistant fisheye, 180 deg across, trees and buildings on the horizon):
      startrack render --projection equidistant --fov-deg 180 --size 800x800 --ra 80 --dec 40 --mag-max 5.5 \
          --horizon random --extinction-mag 0.2 --seed 5 -o allsky.png > allsky.json
    \b
    Example (star lists as a low-Earth-orbit camera sees them on 22 September 2026: the Earth's
    velocity and the camera's own, turning once an orbit, make stellar aberration):
      startrack render --stars-only --count 5 --fov-deg 15 --size 1024x1024 --sigma-px 0.3 --seed 3 \\
          --time 2026-09-22T12:00:00Z --velocity-km-s 7.5,0,0 --orbit-period-s 5400 > leo.jsonl
    """
    import math
    import os

    import numpy as np

    from startrack.apparent import parse_velocity
    from startrack.catalog import load_catalog
    from startrack.cli.paths import numbered_path
    from startrack.errors import BadInputError
    from startrack.formats.frame import FrameWriter
    from startrack.imageio import check_image_output
    from startrack.progress import ProgressBar
    from startrack.render import RenderRun, Scene, Sensor
    from startrack.rotations import normalize_quaternion, quaternion_to_dcm, radec_roll_to_dcm
    from startrack.timeutil import julian_year, parse_time

    cam = camera_from_options(camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2,
                              default_size="1024x1024", projection=projection, k3=k3, k4=k4)
    if count < 1:
        raise BadInputError("--count", None, f"must be at least 1, got {count}")
    from startrack.imageio import max_image_pixels
    from startrack.render import MAX_FALSE_STARS

    if not 0 <= false_stars <= MAX_FALSE_STARS:
        raise BadInputError("--false-stars", None, f"must be in [0, {MAX_FALSE_STARS}], got {false_stars}")
    if not stars_only and cam.width * cam.height > max_image_pixels():
        raise BadInputError("--size", None, f"{cam.width}x{cam.height} is more than {max_image_pixels()} pixels "
                            "(STARTRACK_MAX_IMAGE_PIXELS); use --stars-only for star lists of any size")
    if frames < 1:
        raise BadInputError("--frames", None, f"must be at least 1, got {frames}")
    if not frame_interval_s > 0:
        raise BadInputError("--frame-interval-s", None, f"must be positive, got {frame_interval_s}")
    if not 0 <= drop_fraction < 1:
        raise BadInputError("--drop-fraction", None, f"must be in [0, 1), got {drop_fraction}")
    if max_stars is not None and max_stars < 1:
        raise BadInputError("--max-stars", None, f"must be at least 1, got {max_stars}")
    if sigma_px is not None and sigma_arcsec is not None:
        raise BadInputError("--sigma-px", None, "give --sigma-px or --sigma-arcsec, not both")
    noise_px = 0.0
    if sigma_px is not None:
        noise_px = sigma_px
    elif sigma_arcsec is not None:
        noise_px = sigma_arcsec / cam.pixel_scale_arcsec
    if not noise_px >= 0:
        raise BadInputError("--sigma-px", None, "must be >= 0")
    if (sigma_px is not None or sigma_arcsec is not None or max_stars or drop_fraction) and not stars_only:
        raise BadInputError("--sigma-px", None, "--sigma-px/--sigma-arcsec/--max-stars/--drop-fraction need --stars-only "
                            "(with an image, centroid noise comes from the pixels)")
    if not stars_only:
        if output is None:
            raise BadInputError("--output", None, "an image file is needed (e.g. -o sky.png), or use --stars-only")
        if count * frames > 1 and os.path.splitext(output)[1].lower() in (".png", ".tif", ".tiff", ".fits", ".fit"):
            # A numbered set goes into its own folder, made on demand.
            os.makedirs(os.path.dirname(os.path.abspath(output)), exist_ok=True)
        check_image_output(output)
        if preview is not None:
            if os.path.splitext(preview)[1].lower() != ".png":
                raise BadInputError(preview, None, "the preview is an 8-bit PNG: name it .png")
            if count * frames > 1:
                os.makedirs(os.path.dirname(os.path.abspath(preview)), exist_ok=True)
            from startrack.formats.atomic import check_writable

            check_writable(preview)
    elif output is not None:
        raise BadInputError("--output", None, "--stars-only writes no image; drop --output")
    elif preview is not None:
        raise BadInputError("--preview", None, "--stars-only writes no image; drop --preview")

    attitude = None
    if quaternion is not None:
        if ra is not None or dec is not None:
            raise BadInputError("--quaternion", None, "give either --quaternion or --ra/--dec, not both")
        q = np.array(_floats(quaternion, "--quaternion", 4))
        if not np.all(np.isfinite(q)):
            raise BadInputError("--quaternion", None, f"must be finite, got {quaternion}")
        if abs(np.linalg.norm(q) - 1.0) > 1e-6:
            raise BadInputError("--quaternion", None, f"must be a unit quaternion, its norm is {np.linalg.norm(q):.6g}")
        attitude = quaternion_to_dcm(normalize_quaternion(q))
    elif ra is not None or dec is not None:
        if ra is None or dec is None:
            raise BadInputError("--ra" if ra is None else "--dec", None, "--ra and --dec go together")
        if not (math.isfinite(ra) and math.isfinite(dec) and -90 <= dec <= 90 and math.isfinite(roll)):
            raise BadInputError("--dec", None, f"need finite --ra, --roll and -90 <= --dec <= 90, got {ra}, {dec}, {roll}")
        attitude = radec_roll_to_dcm(ra, dec, roll)
    if attitude is not None and count > 1:
        raise BadInputError("--count", None, "random attitudes (--count) cannot be combined with a given attitude")

    if stars_only:
        for flag, used in (("--cosmic-rays", cosmic_rays), ("--dark-subtracted", dark_subtracted),
                           ("--vignetting", vignetting < 1), ("--gradient", gradient > 1),
                           ("--nebulosity-e-per-s", nebulosity_e_per_s > 0), ("--foreground", foreground)):
            if used:
                raise BadInputError(flag, None, "is a nuisance of images; drop it or --stars-only")
    sensor = Sensor(zero_point, exposure_ms, psf_sigma_px, full_well_e, int(bit_depth), gain_e_per_dn, bias_dn,
                    read_noise_e, dark_current_e_per_s, background_e_per_s, prnu, hot_pixels, not no_noise,
                    dark_subtracted, cosmic_rays, vignetting)
    if mag_max is None:
        # The deep catalog goes to Hp 14.6: render what this sensor can detect (about Hp 8.1 by default).
        mag_max = round(sensor.detection_limit_mag(), 2)
    scene = Scene(mag_max, mag_noise, false_stars, focal_error_pct, tuple(_floats(rate_deg_s, "--rate-deg-s", 3)),
                  foreground=foreground, foreground_fraction=foreground_fraction,
                  foreground_e_per_s=foreground_e_per_s, nebulosity_e_per_s=nebulosity_e_per_s, gradient=gradient,
                  mirror=mirror, horizon=horizon, extinction_mag=extinction_mag, ground_lights=ground_lights)
    t0 = parse_time(start_time) if start_time else None
    cat = load_catalog(catalog, mag_max=mag_max)
    if mag_max is not None:
        cat = cat.filter_magnitude(None, mag_max)
        if len(cat) == 0:
            raise BadInputError("--mag-max", None, f"no catalog star is at or brighter than {mag_max}")
    if t0 is not None:
        cat = cat.propagate(julian_year(t0))
    if resume and (documents == "-" or frame_seed is not None):
        raise BadInputError("--resume", None, "needs --documents FILE, without --frame-seed")
    if seed is None and resume:
        seed = _seed_of(documents)
    if seed is None:
        seed = int(np.random.SeedSequence().entropy % (2**31))
    params = {k: v for k, v in dict(
        catalog=catalog or "shipped", catalog_sha256=cat.checksum(), sensor=sensor.to_dict(),
        scene={"mag_limit": mag_max, "mag_noise": mag_noise, "false_stars": false_stars,
               "focal_error_pct": focal_error_pct, "rate_deg_s": list(scene.rate_deg_s),
               "foreground": foreground, "foreground_fraction": foreground_fraction if foreground else None,
               "foreground_e_per_s": foreground_e_per_s, "nebulosity_e_per_s": nebulosity_e_per_s,
               "gradient": gradient, "mirror": mirror, "horizon": horizon,
               "extinction_mag": extinction_mag or None, "ground_lights": ground_lights or None},
        frames=frames, frame_interval_s=frame_interval_s, count=count, stars_only=stars_only,
        sigma_px=noise_px if stars_only else None, max_stars=max_stars, drop_fraction=drop_fraction,
        time=start_time, aberration=not no_aberration, velocity_km_s=velocity_km_s,
        orbit_period_s=orbit_period_s).items()}
    black = ()
    if blackout:
        try:
            start, n_black = (int(v) for v in blackout.split(":"))
        except ValueError:
            raise BadInputError("--blackout", None, f"expected START:COUNT, got {blackout!r}") from None
        if start < 0 or n_black < 1:
            raise BadInputError("--blackout", None, f"expected START >= 0 and COUNT >= 1, got {blackout!r}")
        black = tuple(range(start, start + n_black))
        params["blackout"] = blackout
    run = RenderRun(cat, cam, sensor, scene, seed, attitude, count, frames, frame_interval_s, t0, stars_only,
                    noise_px, max_stars, drop_fraction,
                    (lambda index: numbered_path(output, index, count * frames)) if output else None,
                    frame_seed, params, black, aberration=not no_aberration,
                    velocity_km_s=tuple(parse_velocity(velocity_km_s, "--velocity-km-s")) if velocity_km_s else None,
                    orbit_period_s=orbit_period_s)
    if orbit_period_s and not velocity_km_s:
        raise BadInputError("--orbit-period-s", None, "needs --velocity-km-s")
    if frame_seed is not None and run.total != 1:
        raise BadInputError("--frame-seed", None, "re-renders one frame: drop --count/--frames")
    skipped = 0
    if resume:
        import dataclasses

        skipped = _keep_done(documents, seed, params, frames, cam.to_dict())
        run = dataclasses.replace(run, count=count - skipped // frames, first_index=skipped)
    bar = ProgressBar("render", quiet)
    n_stars = 0
    from startrack.cluster import TaskFailure

    previews = None if preview is None else _ImagePath(preview, count * frames)
    with FrameWriter(documents, resume=resume, section="render") as writer:
        if scheduler is None:
            results = ((i, [item]) for i, item in enumerate(_write_images(run.frames_iter(), previews)))
        else:
            # Chunks of random attitudes (or of whole sequences) rendered by the Dask workers, which write
            # their image files themselves (a shared filesystem); the documents come back in order.
            import dataclasses

            from startrack.cluster import chunks, default_chunk, ordered_map

            if output:
                run = dataclasses.replace(run, image_path=_ImagePath(os.path.abspath(output), count * frames))
            # --resume: only the sequences not yet in the documents go to the cluster (run.first_index on)
            parts = [dataclasses.replace(run, count=b - a, first_index=run.first_index + a * frames)
                     for a, b in chunks(run.count, default_chunk(run.count, jobs))]
            previews = None if preview is None else _ImagePath(os.path.abspath(preview), count * frames)
            results = ordered_map(_render_chunk, [(part, previews) for part in parts], jobs=jobs, scheduler=scheduler)
        done = 0
        for _, docs in results:  # each chunk's documents written (and flushed) as it arrives, in order
            if isinstance(docs, TaskFailure):
                raise BadInputError("--scheduler", None, f"a chunk of frames failed on the cluster: {docs.error}")
            for doc in docs:
                if scheduler is not None and output and "path" in doc["image"]:
                    # as the user named it (the number of the whole set's frame, --resume or not)
                    doc["image"]["path"] = numbered_path(output, skipped + done, count * frames)
                writer.write(doc)
                n_stars += len(doc["truth"]["stars"])
                done += 1
                bar(done, run.total)
    if skipped:
        info(quiet, f"render: {skipped} frame(s) already in {documents} (--resume)")
    info(quiet, f"render: {run.total} frame(s), {n_stars / max(run.total, 1):.1f} catalog stars per frame on average, "
                f"seed {seed}"
                + (f", images {output if run.total == 1 else os.path.splitext(output)[0] + '-NNNN' + os.path.splitext(output)[1]}"
                   if output else ""))


def _seed_of(documents):
    """The ``render.seed`` of the first document of ``documents`` (``--resume`` without ``--seed``), or None."""
    import json
    import os

    if not os.path.exists(documents):
        return None
    with open(documents, "rb") as fh:
        line = fh.readline()
    try:
        seed = json.loads(line)["render"]["seed"]
    except (ValueError, KeyError, TypeError):
        return None
    return int(seed) if isinstance(seed, int) else None


def _keep_done(documents, seed, params, frames, camera):
    """``--resume``: check the complete documents of ``documents`` are this run's frames, in order, and cut the
    file after the last whole sequence; returns the frames kept.

    Every line must be a ``render`` document of the same ``seed``, parameters and camera with ``frame_index`` its line
    number: anything else is refused (``BadInputError`` naming the line), the file untouched.
    """
    import json
    import os

    from startrack.errors import BadInputError
    from startrack.formats.frame import _loads, read_finished

    if not os.path.exists(documents):
        return 0
    read_finished(documents, "render")  # every complete line a frame document with a render section
    expected = json.loads(json.dumps(params))
    ends = []
    with open(documents, "rb") as fh:
        good = 0
        for raw in fh:
            if not raw.endswith(b"\n"):
                break
            try:
                doc = _loads(raw.decode("utf-8"))
            except (ValueError, UnicodeDecodeError):
                break
            where = f"{documents}:{len(ends) + 1}"
            rec = doc["render"]
            if rec.get("seed") != seed:
                raise BadInputError(where, "render.seed", f"is {rec.get('seed')}, not this run's {seed}")
            if rec.get("params") != expected:
                raise BadInputError(where, "render.params", "differ from this run's options: give the same options")
            cam = json.loads(json.dumps(camera))
            if doc.get("camera") != cam:
                given = doc.get("camera") if isinstance(doc.get("camera"), dict) else {}
                key = next((k for k in sorted(set(cam) | set(given)) if cam.get(k) != given.get(k)), "")
                raise BadInputError(where, f"camera.{key}", f"is {given.get(key)!r}, this run's {cam.get(key)!r}: "
                                                            "give the same options")
            if rec.get("frame_index") != len(ends):
                raise BadInputError(where, "render.frame_index", f"is {rec.get('frame_index')}, expected {len(ends)}")
            good += len(raw)
            ends.append(good)
    keep = len(ends) // frames * frames
    with open(documents, "r+b") as fh:
        fh.truncate(ends[keep - 1] if keep else 0)
    return keep
