"""Kernels that start fast: compiled ahead of time when possible, else by numba on first use.

A command-line call is a fresh process.  With numba alone it pays ~0.4 s to
import numba and ~0.2 s to initialise its compiler target before the first
kernel runs (then ~10 ms per kernel loaded from numba's on-disk cache), even
when every kernel is cached: most of a one-image `startrack solve`.

So every kernel of :mod:`startrack._kernels` is declared with this module's
:func:`njit`, which returns a :class:`LazyKernel` instead of a numba
dispatcher.  A call goes to

1. the ahead-of-time (AOT) build, when ``startrack cache build`` (run by
   ``make install``) has compiled one for exactly this code, numba, numpy and
   Python, and it holds an entry for exactly the argument types of the call
   (dtype, dimensions, memory layout, writability, alignment; a Python
   ``float`` is ``float64``, an ``int`` ``int64``); such a process never
   imports numba; else
2. numba's just-in-time dispatcher, as before (``cache=True``): on the first
   such call numba is imported and every lazy kernel gets its dispatcher; numba
   types a lazy kernel met as a global inside another kernel as that dispatcher,
   so kernels calling kernels compile as ordinary numba code.

The AOT build is made with :mod:`numba.pycc` from the signatures of the kernels
called from Python (entry points) that the process building it has compiled (the warm-up of the solver and the identification
algorithms), into ``kernels-<tag>.so`` in the cache directory beside the
pattern index's (see :func:`kernels_dir`); ``<tag>`` hashes the kernels' source (and
``solve.py``, whose warm-up chooses the signatures), numba's, numpy's and
Python's versions, so an edited kernel or an upgrade simply misses the build
(and falls back to numba) until the next ``startrack cache build``.  Parallel
kernels (``parallel=True``) and kernels that are only inlined into others are
never built ahead of time.  ``STARTRACK_AOT=0`` turns the AOT build off.

Exact type matching matters: an AOT entry called with another dtype reads
memory as the wrong type, so the key below is strict and anything it does not
know (tuples, lists, ``None``, records) goes to numba.
"""
from __future__ import annotations

import functools
import hashlib
import importlib.util
import json
import os
import sys

import numpy as np

__all__ = ["njit", "prange", "LazyKernel", "kernels_dir", "aot_path", "build_aot", "aot_loaded", "aot_intact"]

_KERNELS: list = []          # every LazyKernel, in definition order
_MATERIALISED = False        # numba imported and every lazy kernel bound to a dispatcher
_AOT_TABLE: dict | None = None   # qualified name -> {argument key: compiled function}; {} when none


class _PRange:
    """Stands for ``numba.prange`` until numba is imported (replaced before anything compiles)."""

    def __call__(self, *args):
        return range(*args)


prange = _PRange()


def njit(*args, **options):
    """``numba.njit``'s decorator, lazily: ``@njit(cache=True)`` or ``@njit``."""
    if args and callable(args[0]) and not options:
        return njit()(args[0])

    def wrap(py_func):
        kernel = LazyKernel(py_func, options)
        _KERNELS.append(kernel)
        if _MATERIALISED:
            kernel._dispatcher = _dispatcher(kernel)
        return kernel

    return wrap


def _qualname(py_func) -> str:
    return f"{py_func.__module__.rsplit('.', 1)[-1]}.{py_func.__qualname__}"


# The per-call key: cheap to compute (a call's overhead is part of every kernel's cost).  An array's is
# (dtype, ndim, layout | writeable/aligned bits of ``flags.num``) with layout 1 = C, 2 = F, 0 = any; a
# scalar's its dtype string.  numba types an array contiguous both ways (1-D) as C, as here.
_C, _F, _ALIGNED, _WRITEABLE = 0x1, 0x2, 0x100, 0x400
_LAYOUT = {"C": _C, "F": _F, "A": 0}
_SCALARS = {float: "<f8", int: "<i8", bool: "|b1"}
for _t in (np.float64, np.float32, np.int64, np.int32, np.int16, np.int8, np.uint64, np.uint32, np.uint16,
           np.uint8, np.bool_):
    _SCALARS[_t] = np.dtype(_t).str
_NDARRAY = np.ndarray
# An array's key bits from its ``flags.num``, looked up rather than computed per argument.
_FLAG_BITS = _C | _F | _ALIGNED | _WRITEABLE
_KEY_BITS = tuple((_C if n & _C else (_F if n & _F else 0)) | (n & (_ALIGNED | _WRITEABLE)) for n in range(_FLAG_BITS + 1))


def _call_key(args):
    """The exact type of the arguments, as numba's ``typeof`` would see them; None when unsupported.

    Python ``int`` maps to int64 (None beyond its range), ``float`` to float64.  Array subclasses,
    arrays of other kinds than bool/int/float, tuples, lists, None, records: None.
    """
    out = []
    for a in args:
        t = type(a)
        if t is float:         # most arguments
            out.append("<f8")
        elif t is _NDARRAY:
            dtype = a.dtype
            if dtype.kind not in "biuf":
                return None
            out.append((dtype, a.ndim, _KEY_BITS[a.flags.num & _FLAG_BITS]))
        else:
            k = _SCALARS.get(t)
            if k is None or (t is int and not -(2**63) <= a < 2**63):
                return None
            out.append(k)
    return tuple(out)


def _fast_key(key):
    """A manifest key (dtype string, ndim, layout letter, writeable, aligned per array) as :func:`_call_key`'s."""
    out = []
    for k in key:
        if isinstance(k, (tuple, list)):
            dt, ndim, layout, writeable, aligned = k
            out.append((np.dtype(dt), int(ndim),
                        _LAYOUT[layout] | (_WRITEABLE if writeable else 0) | (_ALIGNED if aligned else 0)))
        else:
            out.append(k)
    return tuple(out)


def _numba_key(ty):
    """The key of a numba type (the build side of :func:`_call_key`, via :func:`_fast_key`); None when unsupported."""
    from numba.core import types
    from numba.np.numpy_support import as_dtype

    if isinstance(ty, types.Array):
        try:
            dt = as_dtype(ty.dtype)
        except Exception:  # noqa: BLE001 - records and other dtypes stay with numba
            return None
        if dt.kind not in "biuf":
            return None
        return (dt.str, ty.ndim, ty.layout, bool(ty.mutable), bool(ty.aligned))
    if isinstance(ty, types.Boolean):
        return "|b1"
    if isinstance(ty, (types.Integer, types.Float)):
        return as_dtype(ty).str
    return None


class LazyKernel:
    """A kernel that runs its AOT build when it has one for the arguments, else numba's dispatcher."""

    def __init__(self, py_func, options: dict):
        self.py_func = py_func
        self.options = dict(options)
        self.qualname = _qualname(py_func)
        self._dispatcher = None
        self._aot = None
        self.entry = False
        functools.update_wrapper(self, py_func)

    def __call__(self, *args):
        self.entry = True          # called from Python: an entry point of the AOT build
        aot = self._aot
        if aot is None:
            aot = self._aot = _aot_table().get(self.qualname, {})
        if aot:
            fn = aot.get(_call_key(args))
            if fn is not None:
                return fn(*args)
        return self.dispatcher(*args)

    def resolve(self, args):
        """What a call with ``args`` runs: the AOT entry for their exact types, else numba's dispatcher.

        For a caller making many calls whose arguments have the same types by construction (it
        makes them): it looks the entry up once instead of computing the key per call."""
        self.entry = True
        aot = self._aot
        if aot is None:
            aot = self._aot = _aot_table().get(self.qualname, {})
        if aot:
            fn = aot.get(_call_key(args))
            if fn is not None:
                return fn
        return self.dispatcher

    @property
    def dispatcher(self):
        """The numba dispatcher (numba imported and every lazy kernel bound on first use)."""
        if self._dispatcher is None:
            _materialise()
        return self._dispatcher

    @property
    def signatures(self) -> list:
        """Argument types this process can run without compiling (AOT entries or compiled overloads)."""
        aot = self._aot if self._aot is not None else _aot_table().get(self.qualname, {})
        compiled = list(self._dispatcher.signatures) if self._dispatcher is not None else []
        return list(aot) + compiled

    def __getattr__(self, name):
        # overloads, inspect_types, parallel_diagnostics ...: numba's own.
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self.dispatcher, name)

    def __repr__(self) -> str:
        return f"<LazyKernel {self.qualname}>"


def _dispatcher(kernel):
    """numba's dispatcher of ``kernel``, whose calls from other kernels compile for the arguments' plain types.

    numba types a call between kernels with the arguments' literal types when it knows them (``f(x, 0)``, or a
    counter ``k = 0 ... k += 1`` whose type is still ``Literal[int](0)`` in type inference's first pass) and
    compiles the callee for each: a second specialization of ``f``, typed, lowered and optimised again, for
    nothing the kernels need (none of them asks for a literal).  Here a nested call's literal arguments are
    replaced by their plain types (``int64``, ``bool``) before numba looks for or compiles a specialization.
    """
    import numba
    from numba.core import types

    dispatcher = numba.njit(**kernel.options)(kernel.py_func)
    literal_template = dispatcher.get_call_template

    def get_call_template(args, kws):
        return literal_template(tuple(types.unliteral(a) for a in args),
                                {name: types.unliteral(a) for name, a in kws.items()})

    dispatcher.get_call_template = get_call_template
    return dispatcher


def _materialise() -> None:
    """Import numba and bind every lazy kernel to a dispatcher.

    Kernels calling kernels see lazy kernels as globals: numba types one as its
    dispatcher (registered here), so they compile as ordinary numba calls.  The
    ``prange`` stand-ins become ``numba.prange``.
    """
    global _MATERIALISED, prange
    import numba
    from numba.core.typing.typeof import typeof_impl

    if not _MATERIALISED:
        @typeof_impl.register(LazyKernel)
        def _typeof_lazy(val, c):
            return typeof_impl(val.dispatcher, c)

    for k in _KERNELS:
        if k._dispatcher is None:
            k._dispatcher = _dispatcher(k)
    _MATERIALISED = True
    prange = numba.prange
    for name, mod in list(sys.modules.items()):
        if name.startswith("startrack._kernels") and mod is not None:
            space = vars(mod)
            for attr, value in list(space.items()):
                if isinstance(value, _PRange):
                    space[attr] = numba.prange


# ---------------------------------------------------------------- the AOT build

def _versions() -> str:
    return f"numba {_numba_version()}; numpy {np.__version__}; python {sys.version}; {sys.platform}"


def _numba_version() -> str:
    """numba's installed version, without importing numba or importlib.metadata (~20 ms of every process's
    start-up): the name of the one ``numba-VERSION.dist-info`` beside the package, else importlib.metadata."""
    spec = importlib.util.find_spec("numba")
    if spec is not None and spec.origin:
        site = os.path.dirname(os.path.dirname(spec.origin))
        try:
            found = [n for n in os.listdir(site) if n.startswith("numba-") and n.endswith(".dist-info")]
        except OSError:
            found = []
        if len(found) == 1:
            return found[0][len("numba-"):-len(".dist-info")]
    from importlib.metadata import version

    return version("numba")


def _cpu_id() -> str:
    """This machine's CPU model and instruction-set flags (cheap: no LLVM), for the build's tag.

    The build is compiled for the host CPU (as numba's JIT compiles), so another CPU model sharing the
    cache directory (a cluster's home directory) misses it and uses numba's JIT until it builds its own.
    """
    try:
        with open("/proc/cpuinfo") as f:
            text = f.read(65536).split("\n\n", 1)[0]      # the first processor's block
        keep = [line for line in text.splitlines() if line.split(":")[0].strip() in ("vendor_id", "model name", "flags",
                                                                                        "Features", "CPU part")]
        if keep:
            return "\n".join(keep)
    except OSError:
        pass
    import platform

    return f"{platform.machine()} {platform.processor()}"


#: The modules (relative to the package) whose warm-ups run in the AOT build (:func:`startrack.solve.warm_for_build`).
_WARM_UP_SOURCES = ("solve.py", "patterns.py", "centroid.py", "identify/__init__.py", "identify/catalog_match.py")


@functools.lru_cache(maxsize=1)
def _tag() -> str:
    """Hash of the kernels' source, the versions that compile and run them, and the CPU they are built for."""
    here = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha1(_versions().encode())
    h.update(_cpu_id().encode())
    files = [os.path.join(here, n) for n in sorted(os.listdir(here)) if n.endswith(".py")]
    # The warm-up that decides which signatures the build holds: solve.py's warm_for_build and the warm-ups it
    # calls (a change of theirs alone would leave a build without the entries they now make).
    package = os.path.dirname(here)
    files += [os.path.join(package, *name.split("/")) for name in _WARM_UP_SOURCES]
    for path in files:
        with open(path, "rb") as f:
            h.update(os.path.basename(path).encode() + b"\0" + f.read())
    return h.hexdigest()[:12]


def kernels_dir() -> str:
    """``$STARTRACK_KERNELS``, else ``$XDG_CACHE_HOME/startrack/kernels``, else ``~/.cache/startrack/kernels``.

    Not under ``$STARTRACK_CACHE``: the build depends on the code, not on the
    star data a cache directory holds, and one build serves every cache.
    """
    return os.environ.get("STARTRACK_KERNELS") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "startrack", "kernels")


def aot_path(directory: str | None = None) -> str:
    """Where the AOT build of this code's kernels lives (it may not exist)."""
    return os.path.join(directory or kernels_dir(), f"kernels-{_tag()}.so")


def _aot_table() -> dict:
    global _AOT_TABLE
    if _AOT_TABLE is None:
        _AOT_TABLE = _load_aot()
    return _AOT_TABLE


def _load_aot() -> dict:
    if os.environ.get("STARTRACK_AOT", "1") == "0":
        return {}
    path = aot_path()
    try:
        with open(path[:-3] + ".json") as f:
            manifest = json.load(f)
    except (OSError, ValueError):
        return {}
    if not aot_intact(path, manifest):
        return {}
    spec = importlib.util.spec_from_file_location(manifest["module"], path)
    if spec is None:
        return {}
    try:
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    except (ImportError, OSError):
        return {}
    table: dict = {}
    for qualname, entries in manifest["kernels"].items():
        table[qualname] = {_fast_key(key): getattr(mod, symbol) for symbol, key in entries}
    return table


def _file_sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def aot_intact(path: str, manifest: dict | None = None) -> bool:
    """Whether the AOT build at ``path`` is the one its manifest describes (its ``sha256``).

    A damaged library would be loaded and its machine code run: a crash, or wrong numbers.  The
    checksum is read once per file state: a ``.checked`` stamp beside it holds the file's inode, size
    and times when it matched, so that later start-ups only ``stat`` it (as the pattern index does).
    A mismatch is said once on stderr; the kernels then run under numba's JIT.
    """
    try:
        if manifest is None:
            with open(path[:-3] + ".json") as f:
                manifest = json.load(f)
        want = manifest.get("sha256")
        st = os.stat(path)
    except (OSError, ValueError, AttributeError):
        return False
    if not isinstance(want, str):
        return False                # a build from before checksums: not trusted, rebuilt by `cache build`
    stamp = [st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns, want]
    checked = path[:-3] + ".checked"
    try:
        with open(checked) as f:
            if json.load(f) == stamp:
                return True
    except (OSError, ValueError):
        pass
    try:
        got = _file_sha256(path)
    except OSError:
        return False
    if got != want:
        sys.stderr.write(f"startrack: WARNING: compiled kernels {path}: sha256: does not match its build's: the file "
                         "is damaged; running numba's just-in-time kernels (`startrack cache build` rebuilds it)\n")
        return False
    try:
        tmp = f"{checked}.{os.getpid()}"
        with open(tmp, "w") as f:
            json.dump(stamp, f)
        os.replace(tmp, checked)
    except OSError:
        pass
    return True


def aot_loaded() -> bool:
    """Whether this process runs kernels from an AOT build."""
    return bool(_aot_table())


def build_aot(directory: str | None = None, kernels=None) -> tuple[str, int]:
    """Compile the signatures this process has compiled with numba into an AOT build.

    Parameters
    ----------
    directory : str, optional
        Directory of the build (default: :func:`kernels_dir`).
    kernels : iterable of LazyKernel, optional
        Which kernels (default: all that have compiled signatures).

    Returns
    -------
    (path, entries) : the ``.so`` written and its number of entry points.
    """
    _materialise()
    from llvmlite import binding as llvm
    from numba.core import codegen

    path = aot_path(directory)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    module = f"_startrack_kernels_{_tag()}"

    # numba.pycc compiles for a generic CPU by default (~40 % slower kernels than numba's JIT); the CPU name
    # alone is not enough either (an LLVM that does not know the model falls back to generic features), so
    # the build gets the host's name and its feature string, as the JIT does.
    cpu, features = llvm.get_host_cpu_name(), llvm.get_host_cpu_features().flatten()
    saved = codegen.AOTCPUCodegen._customize_tm_features
    codegen.AOTCPUCodegen._customize_tm_features = lambda _self: features
    try:
        return _build(path, module, cpu, kernels)
    finally:
        codegen.AOTCPUCodegen._customize_tm_features = saved


def _build(path, module, cpu, kernels):
    """:func:`build_aot`'s compilation (codegen already set for the host)."""
    entries = []
    for k in (list(kernels) if kernels is not None else _KERNELS):
        # Entry points only (kernels called from Python): the others are compiled into them.
        if not k.entry or k.options.get("parallel") or k.options.get("inline") == "always" or k._dispatcher is None:
            continue
        for args in list(k._dispatcher.signatures):
            key = tuple(_numba_key(t) for t in args)
            if None not in key:
                entries.append((k, args, key))
    skipped: list = []
    # ``nogil=True`` kernels release the GIL in the AOT build too (numba.pycc compiles every export with one set
    # of flags, without ``release_gil``): threads of one process then run them at once.
    import numba.pycc.compiler as pycc_compiler

    nogil = {k.py_func for k, _, _ in entries if k.options.get("nogil")}
    compile_extra = pycc_compiler.compile_extra

    def compile_nogil(typing_context, target_context, func, args, return_type, flags, *rest, **kwargs):
        if func in nogil:
            flags = flags.copy()
            flags.release_gil = True
        return compile_extra(typing_context, target_context, func, args, return_type, flags, *rest, **kwargs)

    pycc_compiler.compile_extra = compile_nogil
    from numba.core.pythonapi import PythonAPI

    adapt = PythonAPI.nrt_adapt_ndarray_to_python
    PythonAPI.nrt_adapt_ndarray_to_python = _adapt_with_cached_type(adapt)
    try:
        return _build_entries(path, module, cpu, entries, skipped)
    finally:
        pycc_compiler.compile_extra = compile_extra
        PythonAPI.nrt_adapt_ndarray_to_python = adapt


def _adapt_with_cached_type(adapt):
    """numba's boxing of a returned array (``PythonAPI.nrt_adapt_ndarray_to_python``) with the array's Python type
    unpickled once per process instead of at every return.

    numba embeds that type (``numpy.ndarray``) pickled and unpickles it each time a kernel hands an array back.  Its
    JIT memoises the unpickling; a numba.pycc build calls ``pickle.loads`` every time (~1 us a returned array) and
    keeps the reference it gets (``numpy.ndarray``'s reference count grew by one a call).  Here the unpickled object
    goes to a global of the kernel's LLVM module on its first use and is read from there after: one ``loads`` and
    one reference per kernel and process.  Two threads boxing at once (the GIL is held while boxing) at worst both
    unpickle it once."""
    from llvmlite import ir
    from numba.core import cgutils

    def cached_unserialize(pyapi, structptr):
        name = getattr(structptr, "name", None)
        if not name:         # not a module constant: as numba does it
            return type(pyapi).unserialize(pyapi, structptr)
        builder = pyapi.builder
        module = builder.module
        slot_name = f"{name}.startrack_unpickled"
        slot = module.globals.get(slot_name)
        if slot is None:
            slot = ir.GlobalVariable(module, pyapi.pyobj, slot_name)
            slot.linkage = "internal"
            slot.initializer = ir.Constant(pyapi.pyobj, None)
        with builder.if_then(cgutils.is_null(builder, builder.load(slot)), likely=False):
            builder.store(type(pyapi).unserialize(pyapi, structptr), slot)
        return builder.load(slot)

    def adapt_cached(self, aryty, ary, dtypeptr):
        self.unserialize = functools.partial(cached_unserialize, self)
        try:
            return adapt(self, aryty, ary, dtypeptr)
        finally:
            del self.unserialize

    return adapt_cached


def _build_entries(path, module, cpu, entries, skipped):
    """:func:`_build`'s compilation of ``entries`` (a kernel numba.pycc cannot compile is left to the JIT)."""
    import re
    import tempfile
    import warnings

    from numba.pycc import CC

    while entries:
        cc = CC(module)
        cc.target_cpu = cpu
        manifest: dict = {"module": module, "versions": _versions(), "cpu": cpu, "kernels": {}, "skipped": skipped}
        for n, (k, args, key) in enumerate(entries):
            symbol = f"k{n}_{k.py_func.__name__}"
            cc.export(symbol, k._dispatcher.overloads[args].signature)(k.py_func)
            manifest["kernels"].setdefault(k.qualname, []).append([symbol, key])
        try:
            with tempfile.TemporaryDirectory(dir=os.path.dirname(path)) as tmp:
                cc.output_dir = tmp
                cc.output_file = os.path.basename(path)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    cc.compile()
                os.replace(os.path.join(tmp, os.path.basename(path)), path)
        except Exception as exc:  # noqa: BLE001 - a kernel numba cannot compile ahead of time stays JIT
            # numba.pycc types with slightly different rules (e.g. a variable reused with
            # another type); leave the kernel it names to the JIT and build the rest.
            names = set(re.findall(r"def (\w+)\(", str(exc)))
            keep = [e for e in entries if e[0].py_func.__name__ not in names]
            if not names or len(keep) == len(entries):
                raise
            reason = " ".join(str(exc).split())[:300]
            skipped.extend({"kernel": q, "reason": reason} for q in sorted({e[0].qualname for e in entries
                                                                            if e not in keep}))
            entries = keep
            continue
        manifest["sha256"] = _file_sha256(path)
        with open(path[:-3] + ".json.tmp", "w") as f:
            json.dump(manifest, f)
        os.replace(path[:-3] + ".json.tmp", path[:-3] + ".json")
        return path, len(entries)
    return path, 0
