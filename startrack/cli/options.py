"""Options shared by several commands, defined once, and the error handling."""
from __future__ import annotations

import contextlib
import functools
import os
import sys

import click

from startrack.errors import BadInputError, StartrackError


def input_argument(f):
    return click.argument("input", default="-", metavar="INPUT")(f)


def output_option(help_text="Output file, or - for standard output.", default="-"):
    return click.option("--output", "-o", default=default, show_default=True,
                        type=click.Path(dir_okay=False, allow_dash=True), help=help_text)


seed_option = click.option("--seed", type=int, default=None,
                           help="Seed of the random generator; the same seed gives the same output.")
jobs_option = click.option("--jobs", "-j", type=int, default=1, show_default=True,
                           help="Frames processed at once; the output keeps the input order.")
resume_option = click.option("--resume", is_flag=True,
                             help="Keep the frames already in the -o file (a run cut short) and do only the rest.")
quiet_option = click.option("--quiet", "-q", is_flag=True,
                            help="No progress bar or summary on stderr (errors and failures are still shown).")
catalog_option = click.option("--catalog", type=click.Path(dir_okay=False), default=None,
                              help="Star catalog (startrack.catalog/1 HDF5); default: the shipped Hipparcos catalog.")


def camera_options(f):
    """``--camera FILE`` or ``--fov-deg``/``--focal-length-mm``+``--pixel-pitch-um`` with ``--size``."""
    opts = [
        click.option("--camera", "camera_file", type=click.Path(dir_okay=False, allow_dash=False),
                     default=None, help="Camera JSON (startrack.camera/1, or a frame document's camera)."),
        click.option("--fov-deg", type=float, default=None,
                     help="Horizontal field of view in degrees (with --size)."),
        click.option("--focal-length-mm", type=float, default=None,
                     help="Lens focal length in mm (with --pixel-pitch-um and --size)."),
        click.option("--pixel-pitch-um", type=float, default=None, help="Pixel pitch in micrometres."),
        click.option("--size", type=str, default=None, help="Image size WIDTHxHEIGHT in pixels, e.g. 1024x768."),
        click.option("--k1", type=float, default=None, help="Radial distortion coefficient k1."),
        click.option("--k2", type=float, default=None, help="Radial distortion coefficient k2."),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


def camera_from_options(camera_file=None, fov_deg=None, focal_length_mm=None, pixel_pitch_um=None,
                        size=None, k1=None, k2=None, default_size=None, required=True):
    """Build a :class:`~startrack.camera.Camera` from the camera options (or ``None``)."""
    from startrack.camera import Camera, parse_size

    kw = {}
    if k1 is not None:
        kw["k1"] = k1
    if k2 is not None:
        kw["k2"] = k2
    if camera_file is not None:
        if fov_deg is not None or focal_length_mm is not None:
            raise BadInputError("--camera", None, "give either --camera or --fov-deg/--focal-length-mm, not both")
        cam = load_camera_file(camera_file)
        if kw:
            from dataclasses import replace

            cam = replace(cam, **kw)
        return cam
    if size is None:
        size = default_size
    if fov_deg is None and focal_length_mm is None:
        if required:
            raise BadInputError("--fov-deg", None, "a camera is needed: give --fov-deg and --size, "
                                "--focal-length-mm, --pixel-pitch-um and --size, or --camera FILE")
        return None
    if size is None:
        raise BadInputError("--size", None, "is needed with --fov-deg or --focal-length-mm (e.g. --size 1024x1024)")
    width, height = parse_size(size)
    if fov_deg is not None and focal_length_mm is not None:
        raise BadInputError("--fov-deg", None, "give either --fov-deg or --focal-length-mm, not both")
    if fov_deg is not None:
        if not fov_deg > 0:
            raise BadInputError("--fov-deg", None, f"must be positive, got {fov_deg:g}")
        return Camera.from_fov(fov_deg, width, height, pixel_pitch_um=pixel_pitch_um, **kw)
    if pixel_pitch_um is None:
        raise BadInputError("--pixel-pitch-um", None, "is needed with --focal-length-mm")
    return Camera.from_focal_length_mm(focal_length_mm, pixel_pitch_um, width, height, **kw)


def load_camera_file(path):
    """A camera from a ``startrack.camera/1`` file or from a frame document's ``camera`` section."""
    from startrack.camera import Camera
    from startrack.formats.frame import check_format_tag, read_json_file

    doc = read_json_file(path)
    if "format" in doc and doc["format"] != "startrack.camera/1":
        if str(doc["format"]).startswith("startrack.frame/"):
            check_format_tag(doc, "startrack.frame/1", path)
            doc = doc.get("camera")
            if doc is None:
                raise BadInputError(path, "camera", "is missing")
        else:
            check_format_tag(doc, "startrack.camera/1", path)
    return Camera.from_dict(doc, path)


def command_path() -> str:
    ctx = click.get_current_context(silent=True)
    return ctx.command_path if ctx is not None else "startrack"


def handle_errors(func):
    """Turn library errors into one line on stderr and the right exit status.

    ``BadInputError`` -> exit 2; any other ``StartrackError`` -> exit 1; an
    unexpected exception -> exit 1 with its type and message (the traceback is
    shown only with ``STARTRACK_DEBUG=1``).
    """

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        from startrack.formats.atomic import Terminated, install_signal_cleanup

        install_signal_cleanup()
        if not os.environ.get("STARTRACK_DEBUG"):
            # numpy's RuntimeWarnings (empty slices, 0/0 on degenerate input) are not messages for users:
            # every result they could touch is checked and reported as a status with a reason.
            import warnings

            warnings.filterwarnings("ignore", category=RuntimeWarning)
        try:
            return func(*args, **kwargs)
        except click.exceptions.Exit:
            raise
        except click.ClickException:
            raise
        except StartrackError as exc:
            _echo_err(f"{command_path()}: error: {exc}")
            sys.exit(exc.exit_code)
        except BrokenPipeError:
            # The reader went away (e.g. `| head`): not our failure, like SIGPIPE for a C tool.
            with contextlib.suppress(OSError, ValueError, AttributeError):
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, sys.stdout.fileno())
            sys.exit(0)
        except PermissionError as exc:
            _echo_err(f"{command_path()}: error: {exc.filename}: permission denied")
            sys.exit(2)
        except Terminated:
            _echo_err(f"{command_path()}: terminated (temporary files removed, outputs left as they were)")
            sys.exit(143)
        except KeyboardInterrupt:
            _echo_err(f"{command_path()}: interrupted (temporary files removed, outputs left as they were)")
            sys.exit(130)
        except RecursionError:
            _echo_err(f"{command_path()}: error: input nested too deeply")
            sys.exit(2)
        except MemoryError:
            _echo_err(f"{command_path()}: error: out of memory (see 'Limits' in docs/formats.md)")
            sys.exit(1)
        except Exception as exc:  # noqa: BLE001 - the last line of defence of a CLI
            if os.environ.get("STARTRACK_DEBUG"):
                raise
            msg = str(exc).splitlines()[0] if str(exc) else ""
            _echo_err(f"{command_path()}: internal error: {type(exc).__name__}: {msg} "
                      "(set STARTRACK_DEBUG=1 for a traceback)")
            sys.exit(1)

    return wrapper


def require_stdout() -> None:
    """Refuse (exit 2, one line) a command whose result goes to standard output when it is closed (``>&-``)."""
    if sys.stdout is None or sys.stdout.closed:
        raise BadInputError("<stdout>", None, "is closed: the result has nowhere to go")


def _echo_err(message: str) -> None:
    """One line on stderr; silently nothing if stderr itself is closed."""
    with contextlib.suppress(OSError, ValueError, AttributeError):
        click.echo(message, err=True)


def info(quiet: bool, message: str) -> None:
    """A summary line on stderr, unless ``--quiet``."""
    if not quiet:
        click.echo(message, err=True)
