"""The command-line vocabulary: shared options, validated types, and the error handling.

Every command is a :class:`Command` (``@click.command(..., cls=Command)``), which adds
``-v/--verbose``, accepts the deprecated spellings of :data:`DEPRECATED` (with one
warning on stderr), and checks the option pairs a command declares (``exclusive``:
at most one of them; ``ordered``: the first not above the second).  Numbers are
parsed by :class:`FiniteFloat`, :func:`Int` and :class:`NumberList`, which refuse
NaN, infinities, out-of-range values and empty list items with a usage error that
names the option (exit status 2, one line).  ``click.Choice`` lists come from the
library's registries through :class:`RegistryChoice`, never copied by hand.
"""
from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import re
import sys

import click
from click.core import ParameterSource

from startrack.errors import BadInputError, ParameterError, StartrackError

#: Centroid noise (1 sigma, px) assumed for stars that report no ``sigma_px`` of their own.
DEFAULT_SIGMA_PX = 0.5

#: Old spellings, accepted (with a warning on stderr) for one version: old -> new.
DEPRECATED = {
    "--mag-limit": "--mag-max",
    "--algorithms": "--algorithm",
    "--samples": "--count",
}


# ---------------------------------------------------------------------------------------------
# Types
# ---------------------------------------------------------------------------------------------

class FiniteFloat(click.FloatRange):
    """A finite float, optionally within ``[min, max]`` (``min_open``/``max_open`` exclude the ends).

    NaN and infinities are refused: a NaN limit compares false with everything and
    would silently switch a check off.
    """

    name = "float"

    def __init__(self, min=None, max=None, min_open=False, max_open=False):
        super().__init__(min=min, max=max, min_open=min_open, max_open=max_open, clamp=False)

    def convert(self, value, param, ctx):
        if isinstance(value, str) and not value.strip():
            self.fail("an empty value is not a number", param, ctx)
        rv = click.FloatRange.convert(self, value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value} is not a finite number", param, ctx)
        return rv


def Int(min=None, max=None):
    """An integer within ``[min, max]``."""
    return click.IntRange(min=min, max=max)


class NumberList(click.ParamType):
    """Comma-separated numbers (``0.1,0.2``), each a :class:`FiniteFloat` (or :func:`Int`).

    ``length`` fixes the count (a vector); ``unit`` asks for a unit-norm vector (a quaternion).
    The value is a tuple, or with ``as_text`` the same numbers as canonical text
    ``"0.1,0.2"`` (for bodies that parse the text themselves).
    """

    name = "list"

    def __init__(self, min=None, max=None, min_open=False, max_open=False, integer=False,  # noqa: A002
                 length=None, unit=False, as_text=False):
        self.item = Int(min, max) if integer else FiniteFloat(min, max, min_open, max_open)
        self.integer, self.length, self.unit, self.as_text = integer, length, unit, as_text

    def get_metavar(self, param, ctx=None):
        word = "INT" if self.integer else "X"
        if self.length:
            return ",".join([word] * self.length)
        return f"{word}[,{word}...]"

    def convert(self, value, param, ctx):
        if isinstance(value, (tuple, list)):
            values = tuple(value)
        else:
            text = str(value)
            parts = [p.strip() for p in text.split(",")]
            if any(p == "" for p in parts):
                self.fail(f"empty item in {text!r}: expected comma-separated numbers", param, ctx)
            values = []
            for p in parts:
                try:
                    values.append(self.item.convert(p, param, ctx))
                except click.BadParameter as exc:
                    self.fail(f"item {p!r} of {text!r}: {exc.message}", param, ctx)
            values = tuple(values)
        if self.length is not None and len(values) != self.length:
            self.fail(f"expected {self.length} comma-separated numbers, got {len(values)}", param, ctx)
        if self.unit and abs(math.sqrt(sum(v * v for v in values)) - 1.0) > 1e-6:
            what = "a unit quaternion" if self.length == 4 else "a unit vector"
            self.fail(f"must be {what}, its norm is {math.sqrt(sum(v * v for v in values)):.6g}", param, ctx)
        if self.as_text:
            return ",".join(repr(v) for v in values)
        return values


class Size(click.ParamType):
    """An image size ``WIDTHxHEIGHT`` in pixels, each side in [1, 100000]; the canonical text ``"1024x768"``."""

    name = "size"

    def get_metavar(self, param, ctx=None):
        return "WxH"

    def convert(self, value, param, ctx):
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(value))
        if not m:
            self.fail(f"expected WIDTHxHEIGHT such as 1024x768, got {value!r}", param, ctx)
        w, h = int(m.group(1)), int(m.group(2))
        if not (1 <= w <= 100_000 and 1 <= h <= 100_000):
            self.fail(f"width and height must be in 1..100000 pixels, got {value!r}", param, ctx)
        return f"{w}x{h}"


class RegistryChoice(click.Choice):
    """A ``click.Choice`` whose names come from a registry, read when first needed.

    ``loader`` returns the names (e.g. :func:`startrack.identify.algorithm_names`);
    it runs only when the option is parsed or its help is shown, so ``startrack --help``
    imports no numerical library.  ``retired`` returns names that are no longer
    choices, each with its message (why it went, what to use instead): such a
    name is refused with that message rather than as unknown.
    """

    def __init__(self, loader, case_sensitive=True, retired=None):
        self._loader = loader
        self._names = None
        self.case_sensitive = case_sensitive
        self._retired = retired

    def retired_message(self, value):
        """The message of a retired name, or None."""
        return (self._retired() if self._retired else {}).get(value)

    def convert(self, value, param, ctx):
        message = self.retired_message(value)
        if message is not None:
            self.fail(f"{value!r} is {message}", param, ctx)
        return super().convert(value, param, ctx)

    @property
    def choices(self):
        if self._names is None:
            self._names = tuple(self._loader())
        return self._names

    @choices.setter
    def choices(self, value):
        self._names = tuple(value)


class NameList(click.ParamType):
    """Comma-separated names, each one of a registry's (e.g. ``pyramid,voting``); a tuple, or with ``as_text`` text."""

    name = "names"

    def __init__(self, loader, as_text=False, retired=None):
        self.registry = RegistryChoice(loader, retired=retired)
        self.as_text = as_text

    def get_metavar(self, param, ctx=None):
        return "NAME[,NAME...]"

    def convert(self, value, param, ctx):
        if isinstance(value, (tuple, list)):
            return tuple(value)
        parts = [p.strip() for p in str(value).split(",")]
        if any(p == "" for p in parts):
            self.fail(f"empty item in {value!r}: expected comma-separated names", param, ctx)
        for p in parts:
            message = self.registry.retired_message(p)
            if message is not None:
                self.fail(f"{p!r} is {message}", param, ctx)
            if p not in self.registry.choices:
                self.fail(f"unknown name {p!r}; choose from {', '.join(self.registry.choices)}", param, ctx)
        return ",".join(parts) if self.as_text else tuple(parts)


def identify_algorithms(kind=None):
    """The identification algorithms of the registry (of one database kind if given)."""
    from startrack.identify import algorithm_names, database_kind

    return [name for name in algorithm_names() if kind is None or database_kind(name) == kind]


def retired_algorithms():
    """Former identification algorithms, each with the message that refuses it."""
    from startrack.identify import RETIRED

    return RETIRED


def attitude_methods():
    from startrack.attitude import METHODS

    return list(METHODS)


def centroid_methods():
    from startrack.centroid import METHODS

    return list(METHODS)


# ---------------------------------------------------------------------------------------------
# The command class: deprecated spellings, option constraints, -v/--verbose
# ---------------------------------------------------------------------------------------------

def _configure_logging(ctx, param, value):
    """``-v``: INFO, ``-vv``: DEBUG, on stderr through the logging module (the library logs, never prints)."""
    level = logging.WARNING if not value else (logging.INFO if value == 1 else logging.DEBUG)
    root = logging.getLogger("startrack")
    if not any(getattr(h, "_startrack", False) for h in root.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("startrack: %(levelname)s: %(name)s: %(message)s"))
        handler._startrack = True
        root.addHandler(handler)
    if value or root.level == logging.NOTSET:
        root.setLevel(level)
    return value


verbose_option = click.Option(["--verbose", "-v"], count=True, expose_value=False, callback=_configure_logging,
                              help="More messages on stderr (-v: info, -vv: debug).")


def _given(ctx, name):
    src = ctx.get_parameter_source(name)
    return src is not None and src not in (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)


def flag_of(command, name):
    """The long flag of the parameter ``name`` of ``command`` (``fov_deg`` -> ``--fov-deg``), or None."""
    return param_flags(command).get(name)


def param_flags(command):
    """Parameter name -> its flag, for every option of ``command`` (by click name and by spelling)."""
    flags = {}
    for p in getattr(command, "params", []):
        if not isinstance(p, click.Option) or not p.opts:
            continue
        longs = [o for o in p.opts if o.startswith("--")] or p.opts
        flag = longs[0]
        if p.name:
            flags.setdefault(p.name, flag)
        for o in p.opts:
            if o.startswith("--"):
                flags.setdefault(o[2:].replace("-", "_"), flag)
    return flags


class Command(click.Command):
    """A startrack command: ``-v/--verbose``, deprecated spellings, declared option constraints.

    Parameters (beyond click's)
    ---------------------------
    exclusive : sequence of tuples of parameter names
        At most one of each group may be given.
    ordered : sequence of (low, high) parameter names
        When both are given, low must not exceed high (e.g. ``("mag_min", "mag_max")``).
    rewrite : callable (ctx, args) -> args, optional
        A command's own translation of a deprecated usage.
    """

    def __init__(self, *args, exclusive=(), ordered=(), rewrite=None, **kwargs):
        super().__init__(*args, **kwargs)
        self.rewrite = rewrite
        self.exclusive = tuple(tuple(g) for g in exclusive)
        self.ordered = tuple(tuple(p) for p in ordered)
        if not any(p.name == "verbose" for p in self.params):
            self.params.append(verbose_option)

    def invoke(self, ctx):
        log = logging.getLogger("startrack.cli")
        log.info("%s %s", ctx.command_path, " ".join(f"{k}={v!r}" for k, v in ctx.params.items()))
        return super().invoke(ctx)

    def parse_args(self, ctx, args):
        args = _rewrite_deprecated(self, ctx, list(args))
        if self.rewrite is not None:
            args = self.rewrite(ctx, args)
        rest = super().parse_args(ctx, args)
        self.check_constraints(ctx)
        return rest

    def check_constraints(self, ctx):
        flags = param_flags(self)
        for group in self.exclusive:
            given = [n for n in group if _given(ctx, n)]
            if len(given) > 1:
                raise click.UsageError(f"{flags[given[0]]} and {flags[given[1]]} exclude each other: give one",
                                       ctx)
        for lo, hi in self.ordered:
            a, b = ctx.params.get(lo), ctx.params.get(hi)
            if a is not None and b is not None and a > b:
                raise click.UsageError(f"{flags[lo]} {a:g} is larger than {flags[hi]} {b:g}", ctx)


_warned = set()


def _rewrite_deprecated(command, ctx, args):
    """Old spellings -> new ones (warning once per spelling); stops at ``--``."""
    known = {o for p in command.params for o in getattr(p, "opts", ())}
    out = []
    for i, a in enumerate(args):
        if a == "--":
            out += args[i:]
            break
        name, eq, value = a.partition("=")
        new = DEPRECATED.get(name)
        if new is not None and name not in known and new in known:
            if name not in _warned:
                _warned.add(name)
                click.echo(f"{ctx.command_path}: warning: {name} is deprecated, use {new}", err=True)
            a = new + eq + value
        out.append(a)
    return out


# ---------------------------------------------------------------------------------------------
# Shared options
# ---------------------------------------------------------------------------------------------

def input_argument(f):
    return click.argument("input", default="-", metavar="INPUT")(f)


def output_option(help_text="Output file, or - for standard output.", default="-"):
    return click.option("--output", "-o", default=default, show_default=True,
                        type=click.Path(dir_okay=False, allow_dash=True), help=help_text)


seed_option = click.option("--seed", type=Int(0, 2**63 - 1), default=None,
                           help="Seed of the random generator; the same seed gives the same output.")
jobs_option = click.option("--jobs", "-j", type=Int(1, 1024), default=1, show_default=True,
                           help="Frames processed at once; the output keeps the input order.")
resume_option = click.option("--resume", is_flag=True,
                             help="Keep the frames already in the -o file (a run cut short) and do only the rest.")
quiet_option = click.option("--quiet", "-q", is_flag=True,
                            help="No progress bar or summary on stderr (errors and failures are still shown).")
parity_option = click.option(
    "--parity", type=click.Choice(["auto", "normal", "mirrored"]), default="auto", show_default=True,
    help="Image parity: a mirrored image (a diagonal mirror, rows stored bottom-up) has its stars flipped "
         "(x -> 2 cx - x); auto searches the mirrored stars when the normal ones find nothing.")
def calibration_frame_options(f):
    """``--bias``, ``--dark``, ``--flat``: calibration frames, each repeatable (median-combined)."""
    for flag, what in (("--flat", "Flat frame (an evenly lit exposure; bias removed, scaled to median 1): the "
                                  "image is divided by it."),
                       ("--dark", "Dark frame (same exposure, shutter closed; it holds the bias): subtracted, and "
                                  "its hot pixels replaced by their neighbours' median."),
                       ("--bias", "Bias frame (zero exposure): subtracted when no dark is given; removed from "
                                  "the flat.")):
        f = click.option(flag, flag[2:], multiple=True, type=click.Path(dir_okay=False),
                         help=what + " Repeat to median-combine several.")(f)
    return f


def calibration_from_options(bias, dark, flat):
    """The :class:`~startrack.calibration_frames.CalibrationFrames` of the options, or ``None``."""
    if not (bias or dark or flat):
        return None
    from startrack.calibration_frames import load_calibration_frames

    return load_calibration_frames(bias, dark, flat)


catalog_option = click.option("--catalog", type=click.Path(dir_okay=False), default=None,
                              help="Star catalog: a startrack.catalog/1 HDF5 file, or a name: hipparcos (the "
                                   "shipped catalog, the default) or gaia (Gaia DR3 to G 10 with Hipparcos for "
                                   "the brightest; the extra startrack[gaia]).")


def mag_options(max_help="Faintest catalog star used.", min_help="Brightest catalog star used.", max_default=None,
                with_min=True):
    """``--mag-max`` (faintest) and ``--mag-min`` (brightest): the one spelling of magnitude limits."""
    def deco(f):
        if with_min:
            f = click.option("--mag-min", type=FiniteFloat(-30, 30), default=None, help=min_help)(f)
        return click.option("--mag-max", type=FiniteFloat(-30, 30), default=max_default,
                            show_default=max_default is not None, help=max_help)(f)
    return deco


def sigma_px_option(help_text=None):
    """``--sigma-px``: the centroid noise an algorithm assumes (one rule everywhere)."""
    return click.option("--sigma-px", type=FiniteFloat(0, 100, min_open=True), default=None,
                        help=help_text or ("Centroid noise (1 sigma, px) assumed for stars that report no sigma_px "
                                           f"of their own (default {DEFAULT_SIGMA_PX})."))


#: The camera options exclude each other as sources of the camera.
CAMERA_EXCLUSIVE = (("camera_file", "fov_deg"), ("camera_file", "focal_length_mm"), ("fov_deg", "focal_length_mm"))


def camera_options(f=None, *, fisheye=False):
    """``--camera FILE`` or ``--fov-deg``/``--focal-length-mm``+``--pixel-pitch-um`` with ``--size``.

    ``@camera_options(fisheye=True)`` adds ``--projection``, ``--k3`` and ``--k4`` (the function then
    takes ``projection``, ``k3``, ``k4`` after ``k2``) and lets ``--fov-deg`` reach 360 degrees."""
    if f is None:
        return lambda g: camera_options(g, fisheye=fisheye)
    opts = [
        click.option("--camera", "camera_file", type=click.Path(dir_okay=False, allow_dash=False),
                     default=None, help="Camera JSON (startrack.camera/1, or a frame document's camera)."),
        click.option("--fov-deg", type=FiniteFloat(0, 360 if fisheye else 180, min_open=True, max_open=not fisheye),
                     default=None, help="Horizontal field of view in degrees (with --size)" + (
                         "; a fisheye's may exceed 180 (at most 180 orthographic, below 360 stereographic)."
                         if fisheye else ".")),
        click.option("--focal-length-mm", type=FiniteFloat(0, min_open=True), default=None,
                     help="Lens focal length in mm (with --pixel-pitch-um and --size)."),
        click.option("--pixel-pitch-um", type=FiniteFloat(0, min_open=True), default=None,
                     help="Pixel pitch in micrometres."),
        click.option("--size", type=Size(), default=None, help="Image size WIDTHxHEIGHT in pixels, e.g. 1024x768."),
        click.option("--k1", type=FiniteFloat(-10, 10), default=None, help="Radial distortion coefficient k1."),
        click.option("--k2", type=FiniteFloat(-10, 10), default=None, help="Radial distortion coefficient k2."),
    ]
    if fisheye:
        from startrack.camera import PROJECTIONS

        opts += [
            click.option("--projection", type=click.Choice(list(PROJECTIONS)), default=None,
                         help="The lens's projection (default: pinhole, or the --camera file's); the fisheyes map the "
                              "off-axis angle theta to r = f g(theta_d), theta_d = theta (1 + k1 theta^2 + k2 theta^4 + "
                              "k3 theta^6 + k4 theta^8): equidistant with k1..k4 is OpenCV's fisheye model."),
            click.option("--k3", type=FiniteFloat(-10, 10), default=None, help="A fisheye's distortion coefficient k3."),
            click.option("--k4", type=FiniteFloat(-10, 10), default=None, help="A fisheye's distortion coefficient k4."),
        ]
    for opt in reversed(opts):
        f = opt(f)
    return f


def camera_from_options(camera_file=None, fov_deg=None, focal_length_mm=None, pixel_pitch_um=None,
                        size=None, k1=None, k2=None, default_size=None, required=True, projection=None, k3=None,
                        k4=None):
    """Build a :class:`~startrack.camera.Camera` from the camera options (or ``None``)."""
    from startrack.camera import Camera, parse_size

    kw = {}
    for name, value in (("k1", k1), ("k2", k2), ("projection", projection), ("k3", k3), ("k4", k4)):
        if value is not None:
            kw[name] = value
    if (k3 or k4) and (projection == "pinhole" or (projection is None and camera_file is None)):
        raise BadInputError("--k3" if k3 else "--k4", None, "k3 and k4 are a fisheye's terms: give --projection too")
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


# Library parameters whose flag is not ``--`` + the name with ``-`` for ``_`` (library errors name
# parameters, :class:`startrack.errors.ParameterError`; the command line names its flags).
PARAMETER_FLAGS = {"width": "--size", "height": "--size", "radius_arcsec": "--merge-arcsec", "per_cell": "--uniform",
                   "n_boresights": "--samples", "max_angle_deg": "--fov-deg", "field_w_deg": "--fov-deg",
                   "field_h_deg": "--fov-deg"}


def flag_for(parameter: str) -> str:
    """The command-line flag of a library parameter (``fov_deg`` -> ``--fov-deg``)."""
    return PARAMETER_FLAGS.get(parameter, "--" + parameter.replace("_", "-"))


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
            guard_outputs()
            return func(*args, **kwargs)
        except click.exceptions.Exit:
            raise
        except click.ClickException:
            raise
        except ParameterError as exc:
            click.echo(f"{command_path()}: error: {flag_for(exc.parameter)}: {exc.problem}", err=True)
            sys.exit(exc.exit_code)
        except StartrackError as exc:
            _echo_err(f"{command_path()}: error: {error_message(exc)}")
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
            signal_exc = _signal_behind(exc)
            if signal_exc is not None:
                # a signal raised inside a compiled kernel comes back wrapped (numba: "SystemError: ... returned a
                # result with an exception set"): it is the interruption, not an internal error
                code = getattr(signal_exc, "exit_code", 130)
                what = "terminated" if code == 143 else "interrupted"
                _echo_err(f"{command_path()}: {what} (temporary files removed, outputs left as they were)")
                sys.exit(code)
            if isinstance(exc, OSError) and exc.filename is not None:
                # a file the operating system refused (missing, disk full, too large ...): named, as bad input
                _echo_err(f"{command_path()}: error: {exc.filename}: {exc.strerror or type(exc).__name__}")
                sys.exit(2)
            _echo_err(f"{command_path()}: {internal_error_message(exc)} (set STARTRACK_DEBUG=1 for a traceback)")
            sys.exit(1)

    return wrapper


def internal_error_message(exc) -> str:
    """``internal error while reading FILE: FIELD: Type: message``: an unexpected exception, named by the input it
    happened on (:func:`startrack.errors.input_of`), else by the command's input files."""
    from startrack.errors import input_of

    msg = str(exc).splitlines()[0] if str(exc) else ""
    what = f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__
    where = input_of(exc)
    if where is not None:
        source, fld, read = where
        return f"internal error while {'reading' if read else 'processing'} {source}{f': {fld}' if fld else ''}: {what}"
    from startrack.formats.atomic import registered_inputs

    inputs = registered_inputs()
    if inputs:
        return f"internal error (inputs: {', '.join(inputs[:4])}{' ...' if len(inputs) > 4 else ''}): {what}"
    return f"internal error: {what}"


#: Parameters that name files a command writes (besides any of type :class:`OutputPath`).
OUTPUT_PARAMS = frozenset({"output", "wcs_path", "plot", "fits_out", "matches_out", "csv_path", "documents"})


class OutputPath(click.Path):
    """A file the command writes: never registered as an input (:func:`guard_outputs`)."""


def _path_values(value):
    if isinstance(value, (str, os.PathLike)):
        return [os.fspath(value)]
    if isinstance(value, (tuple, list)):
        return [os.fspath(v) for v in value if isinstance(v, (str, os.PathLike))]
    return []


def guard_outputs(ctx=None) -> None:
    """Refuse (exit 2) an output file that is one of the command's inputs, before any work.

    Inputs are the arguments and the file options (``click.Path``) that are not outputs; ``-`` means
    standard input, which counts when it is a regular file (``< FILE``).  Every output opened later
    through :mod:`startrack.formats.atomic` or a :class:`~startrack.formats.frame.FrameWriter` is checked
    again against every input read since, so a command inherits the rule by using them.
    """
    from startrack.formats.atomic import refuse_input, register_input

    ctx = ctx or click.get_current_context(silent=True)
    if ctx is None:
        return
    outputs = []
    for param in ctx.command.params:
        values = _path_values(ctx.params.get(param.name))
        if param.name in OUTPUT_PARAMS or isinstance(param.type, OutputPath):
            outputs += [v for v in values if v != "-"]
        elif isinstance(param, click.Argument) or isinstance(param.type, click.Path):
            for v in values:
                if v == "-":
                    with contextlib.suppress(AttributeError, ValueError, OSError):
                        register_input(sys.stdin.fileno(), "<stdin>")
                else:
                    register_input(v)
    for path in outputs:
        refuse_input(path)  # only this: a command may create an output's directory itself
    if any(v == "-" for param in ctx.command.params if param.name in OUTPUT_PARAMS or isinstance(param.type, OutputPath)
           for v in _path_values(ctx.params.get(param.name))):
        require_stdout()
    for param in ctx.command.params:
        value = ctx.params.get(param.name)
        if isinstance(param, click.Option) and param.type is click.STRING and isinstance(value, str):
            try:
                value.encode("utf-8")
            except UnicodeEncodeError:
                # an undecodable byte of the command line (a surrogate escape): not text any library can take
                raise BadInputError(flag_of(ctx.command, param.name) or param.name, None,
                                    "is not valid UTF-8 text") from None


class ClosedStdout:
    """Standard output when the process started with it closed (``>&-``): every write is refused.

    Python sets ``sys.stdout`` to None then, and ``click.echo`` drops what it is given: ``cache list >&-``
    and ``--help >&-`` exited 0 with their output lost (issue 41).  In its place, a write raises
    :class:`BadInputError` (exit 2, one line); a command that writes only files is not affected.
    """

    closed = True
    encoding = "utf-8"
    errors = "strict"

    def write(self, text):  # noqa: ARG002 - a stream's signature
        raise BadInputError("<stdout>", None, "is closed: the output has nowhere to go")

    def flush(self):
        return None

    def isatty(self):
        return False

    def writable(self):
        return True

    def fileno(self):
        raise ValueError("standard output is closed")


def install_closed_stdout() -> None:
    """Put a :class:`ClosedStdout` in place of a ``None`` standard output."""
    if sys.stdout is None:
        sys.stdout = ClosedStdout()


def _signal_behind(exc):
    """The ``KeyboardInterrupt`` (Ctrl-C, or SIGTERM's ``Terminated``) an exception was raised from, or None."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def require_stdout() -> None:
    """Refuse (exit 2, one line) a command whose result goes to standard output when it is closed (``>&-``)."""
    if sys.stdout is None or sys.stdout.closed:
        raise BadInputError("<stdout>", None, "is closed: the result has nowhere to go")


def _echo_err(message: str) -> None:
    """One line on stderr; silently nothing if stderr itself is closed."""
    with contextlib.suppress(OSError, ValueError, AttributeError):
        click.echo(message, err=True)


def error_message(exc, command=None):
    """The one-line message of a library error, its parameter names turned into this command's flags.

    The library names parameters (``BadInputError(source, "fov_deg", ...)``); the
    command line knows which flag sets each one, from the click command's own
    parameters (``param.name`` -> its long option).  A ``field`` or ``source`` that
    is a parameter name becomes the flag; parameter names with an underscore
    in the problem text of such an error become flags too.
    """
    if command is None:
        ctx = click.get_current_context(silent=True)
        command = ctx.command if ctx is not None else None
    if not isinstance(exc, BadInputError) or command is None:
        return str(exc)
    flags = param_flags(command)
    key = exc.field if exc.field is not None else exc.source
    if key not in flags or (exc.field is not None and os.path.exists(exc.source)):
        return str(exc)
    problem = re.sub(r"\b[a-z][a-z0-9]*(?:_[a-z0-9]+)+\b", lambda m: flags.get(m.group(0), m.group(0)),
                     exc.problem)
    return f"{flags[key]}: {problem}"


def info(quiet: bool, message: str) -> None:
    """A summary line on stderr, unless ``--quiet``."""
    if not quiet:
        click.echo(message, err=True)


# ---------------------------------------------------------------------------------------------
# Apparent places (issue 39): the frame's time, the observer's velocity, aberration on or off
# ---------------------------------------------------------------------------------------------

def apparent_options(f):
    """``--time``, ``--velocity-km-s``, ``--no-aberration``: how catalog directions become apparent ones."""
    opts = [
        click.option("--time", "obs_time", type=str, default=None,
                     help="ISO-8601 UTC time of every frame (default: each frame's image.time, a FITS DATE-OBS "
                          "or MJD-OBS, EXIF with --utc-offset)."),
        click.option("--velocity-km-s", type=NumberList(-3000, 3000, length=3, as_text=True), default=None,
                     help="The camera's velocity VX,VY,VZ (km/s, GCRS: relative to the Earth's centre, ICRS axes), "
                          "added to the Earth's; default: each frame's observer.velocity_km_s, else 0."),
        click.option("--no-aberration", is_flag=True,
                     help="Compare with catalog directions as if the camera were at rest (no stellar aberration)."),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


def apparent_from_options(obs_time, velocity_km_s, no_aberration):
    """The library's :class:`startrack.apparent.ApparentOptions` of the three options."""
    from startrack.apparent import ApparentOptions, parse_velocity
    from startrack.timeutil import parse_time

    t = parse_time(obs_time, "--time") if obs_time else None
    v = tuple(parse_velocity(velocity_km_s, "--velocity-km-s")) if velocity_km_s else None
    return ApparentOptions(aberration=not no_aberration, time=t, velocity_km_s=v)


class NoTimeNotice:
    """Says once per run, on stderr, that frames had no time (aberration not corrected) and what to add."""

    FRAMES = "add image.time (ISO 8601 UTC) to the frame documents"
    IMAGES = "give the images a FITS DATE-OBS, or EXIF DateTimeOriginal with --utc-offset"

    def __init__(self, command: str, what: str = FRAMES):
        self.command = command
        self.what = what
        self.said = False

    def __call__(self, aberration: str) -> None:
        """``aberration``: the frame's ``FrameApparent.aberration`` (``"no_time"`` is reported once)."""
        if aberration == "no_time" and not self.said:
            self.said = True
            _echo_err(f"{self.command}: no time for a frame, so stellar aberration (up to 20.5 arcsec) is not "
                      f"corrected: {self.what}, or give --time (or --no-aberration to say so)")
