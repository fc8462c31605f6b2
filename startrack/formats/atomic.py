"""Output files that never hurt what was there: atomic regular files, devices written directly.

* A **regular file** (or a new name) is written to a temporary file in the same
  directory, flushed to disk (``fsync``) and renamed onto the destination, so a
  crash, ``kill`` or Ctrl-C never leaves a half-written file: the old file stays
  intact until the new one is complete.  The temporary name carries the writer's
  process id (``.NAME.st<pid>-<random>.part<ext>``); temporary files of dead
  processes are removed the next time anything is written into that directory,
  and this process's own are removed on SIGINT/SIGTERM.
* A **special file** (``/dev/null``, ``/dev/full``, a FIFO, a terminal) is never
  replaced: the output is written into it directly.
* A **symbolic link** is written through: its target is replaced, the link stays.
"""
from __future__ import annotations

import atexit
import contextlib
import errno
import os
import re
import signal
import stat

from startrack.errors import BadInputError

__all__ = [
    "atomic_open",
    "atomic_path",
    "check_writable",
    "clean_stale_temporaries",
    "deferred_signals",
    "input_named_by",
    "install_signal_cleanup",
    "is_special",
    "output_target",
    "refuse_input",
    "register_input",
    "registered_inputs",
    "write_error",
]

_TEMP_RE = re.compile(r"^\.(?P<name>.+)\.st(?P<pid>\d+)-[0-9a-f]{8}\.part")
_LIVE_TEMPS: set[str] = set()
#: (device, inode) -> (name, path or descriptor) of every regular file this process reads (:func:`register_input`).
_INPUTS: dict[tuple[int, int], tuple[str, object]] = {}


def _stat(source):
    try:
        return os.fstat(source) if isinstance(source, int) else os.stat(source)
    except (OSError, TypeError, ValueError):
        return None


def register_input(path, name: str | None = None) -> None:
    """Note that this process reads ``path`` (a path or an open file descriptor): it may not be an output.

    Only regular files count (a device or FIFO is never replaced).  Links and hard links are the same
    file: the file is known by its device and inode (and an entry whose path no longer names that
    inode, a deleted input, is forgotten).
    """
    st = _stat(path)
    if st is not None and stat.S_ISREG(st.st_mode):
        _INPUTS[(st.st_dev, st.st_ino)] = (str(name if name is not None else path), path)


def registered_inputs() -> list[str]:
    """The names of the files this process has read (:func:`register_input`), in the order first read."""
    return list(dict.fromkeys(name for name, _ in _INPUTS.values()))


def input_named_by(path: str) -> str | None:
    """The name under which ``path`` (followed through links) was registered as an input, or None."""
    st = _stat(path)
    if st is None or not stat.S_ISREG(st.st_mode):
        return None
    key = (st.st_dev, st.st_ino)
    entry = _INPUTS.get(key)
    if entry is None:
        return None
    now = _stat(entry[1])
    if now is None or (now.st_dev, now.st_ino) != key:
        del _INPUTS[key]  # the input is gone and its inode reused: not the same file
        return None
    return entry[0]


def output_target(path: str) -> str:
    """The file that writing ``path`` changes: a symbolic link's final target, else ``path``."""
    if os.path.islink(path):
        return os.path.realpath(path)
    return path


def is_special(path: str) -> bool:
    """True for an existing file that is not a regular file (device, FIFO, socket, terminal)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return not stat.S_ISREG(mode) and not stat.S_ISDIR(mode)


def refuse_input(path: str) -> None:
    """Refuse (``BadInputError``) an output that is one of this process's inputs (:func:`register_input`)."""
    same = input_named_by(path)
    if same is not None:
        also = "" if same == str(path) else f" ({same})"
        raise BadInputError(path, None, f"is also an input of this command{also}: writing it would destroy the input; "
                                        "choose another output")


def check_writable(path: str) -> None:
    """Refuse early (``BadInputError``) an output whose directory cannot be written, or that is an input.

    An output that is one of this process's inputs (:func:`register_input`) would destroy the input it
    is computed from (issue 41: ``identify a.jsonl -o a.jsonl`` turned 8 documents into 2 lines).
    """
    refuse_input(path)
    target = output_target(path)
    if os.path.isdir(target):
        raise BadInputError(path, None, "is a directory, expected a file name")
    if is_special(target):
        if not os.access(target, os.W_OK):
            raise BadInputError(path, None, "cannot write: permission denied")
        return
    directory = os.path.dirname(os.path.abspath(target)) or "."
    if not os.path.isdir(directory):
        raise BadInputError(path, None, f"cannot write: directory {directory} does not exist")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise BadInputError(path, None, f"cannot write: directory {directory} is not writable")


def write_error(path: str, exc: OSError) -> BadInputError:
    """The one-line error for an output that failed while being written (disk full, closed pipe ...)."""
    reason = exc.strerror or os.strerror(exc.errno or errno.EIO)
    return BadInputError(path, None, f"cannot write: {reason}")


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_stale_temporaries(directory: str) -> list[str]:
    """Remove temporary files left in ``directory`` by startrack processes that no longer run.

    Returns the removed paths.  Files of live processes (including this one) are kept.
    """
    removed = []
    try:
        names = os.listdir(directory or ".")
    except OSError:
        return removed
    for name in names:
        m = _TEMP_RE.match(name)
        if m is None or _pid_alive(int(m.group("pid"))):
            continue
        full = os.path.join(directory, name)
        with contextlib.suppress(OSError):
            os.remove(full)
            removed.append(full)
    return removed


def _remove_live_temps() -> None:
    for tmp in list(_LIVE_TEMPS):
        with contextlib.suppress(OSError):
            os.remove(tmp)
        _LIVE_TEMPS.discard(tmp)


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when SIGTERM arrives (handled like Ctrl-C, exit status 143)."""

    exit_code = 143


def _on_sigterm(signum, frame):  # noqa: ARG001 - the caller's signature
    # The first SIGTERM ends the process; a second (GNU `timeout` signals the child, then its whole process group)
    # must not raise again while the first is being handled or at interpreter shutdown ("Exception ignored in
    # threading._shutdown" and a traceback after the one-line message).
    with contextlib.suppress(ValueError):
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise Terminated()


def install_signal_cleanup() -> None:
    """Turn SIGTERM into an exception (like SIGINT) so ``finally`` blocks remove temporary files.

    Only has an effect in the main thread; call it once per process (the command line does).
    """
    with contextlib.suppress(ValueError):
        if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
            signal.signal(signal.SIGTERM, _on_sigterm)


@contextlib.contextmanager
def deferred_signals():
    """Hold SIGINT/SIGTERM while a C library (HDF5, OpenCV) writes; raise them afterwards.

    A signal arriving inside h5py's C code or one of its clean-up callbacks would
    otherwise be swallowed and printed as a traceback ("Exception ignored ...");
    held, it is raised (``KeyboardInterrupt`` or :class:`Terminated`) as soon as
    the block ends, where the temporary file is removed and the destination is
    left untouched.  Outside the main thread signals cannot be handled and this
    does nothing.
    """
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []

    def record(signum, frame):  # noqa: ARG001 - the caller's signature
        got.append(signum)

    old = {}
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, record)
    except ValueError:
        pass
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
    if got:
        if got[0] == signal.SIGTERM:
            raise Terminated()
        raise KeyboardInterrupt()


def _fsync_dir(directory: str) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _copy_into_special(tmp: str, dest: str, label: str) -> None:
    try:
        with open(tmp, "rb") as src, open(dest, "wb") as dst:
            import shutil

            shutil.copyfileobj(src, dst, 1 << 20)
    except OSError as exc:
        raise write_error(label, exc) from None


@contextlib.contextmanager
def atomic_path(path: str, suffix: str | None = None):
    """Yield a temporary path beside ``path``; put its content in place on success.

    On success a regular destination is replaced by a rename (after ``fsync``);
    a special file (device, FIFO) receives the bytes directly and is never
    replaced; a symbolic link's target is replaced and the link kept.  On any
    exception, Ctrl-C or SIGTERM the temporary file is removed and ``path`` is
    untouched.  ``suffix`` (default: ``path``'s own extension) lets writers that
    choose a format by extension (OpenCV, astropy, h5py) see the right one.
    """
    check_writable(path)
    target = output_target(path)
    special = is_special(target)
    directory = os.path.dirname(os.path.abspath(target))
    if special:
        import tempfile

        directory = tempfile.gettempdir()
    else:
        clean_stale_temporaries(directory)
    if suffix is None:
        suffix = os.path.splitext(path)[1]
    base = os.path.basename(target) or "output"
    tmp = os.path.join(directory, f".{base}.st{os.getpid()}-{os.urandom(4).hex()}.part{suffix}")
    _LIVE_TEMPS.add(tmp)
    try:
        yield tmp
        if not os.path.exists(tmp):
            raise BadInputError(path, None, "cannot write: the writer produced no file")
        if special:
            _copy_into_special(tmp, target, path)
            return
        with deferred_signals():
            try:
                fd = os.open(tmp, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
                try:
                    mode = stat.S_IMODE(os.stat(target).st_mode)
                except OSError:
                    umask = os.umask(0)
                    os.umask(umask)
                    mode = 0o666 & ~umask
                os.chmod(tmp, mode)
                os.replace(tmp, target)
            except OSError as exc:
                raise write_error(path, exc) from None
            _fsync_dir(directory)
    finally:
        _LIVE_TEMPS.discard(tmp)
        with contextlib.suppress(OSError):
            os.remove(tmp)


@contextlib.contextmanager
def atomic_open(path: str, mode: str = "w", **kwargs):
    """Open a temporary file beside ``path`` and put it in place on success (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        try:
            with open(tmp, mode, **kwargs) as handle:
                yield handle
        except OSError as exc:
            raise write_error(path, exc) from None


atexit.register(_remove_live_temps)
