"""Lazy kernels and their ahead-of-time build (startrack._kernels._jit)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from startrack._kernels import _jit


def _arrays():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(6, 5))
    ro = base.copy()
    ro.flags.writeable = False
    yield base
    yield base.astype(np.float32)
    yield base.astype(np.int64)
    yield base.astype(np.uint8)
    yield base.astype(np.int32)
    yield base.T                      # F order
    yield base[:, ::2]                # neither
    yield base[0]                     # 1-D contiguous
    yield base[:, 0]                  # 1-D strided
    yield ro
    yield np.zeros((0, 4))
    yield np.zeros(3, dtype=bool)
    yield np.arange(4.0).reshape(1, 1, 4)
    yield np.zeros((2, 2), np.uint32)


@pytest.mark.parametrize("value", list(_arrays()) + [1.5, 3, True, np.float32(2.0), np.int64(7), np.float64(1.0),
                                                      np.uint32(4), np.bool_(False)])
def test_argument_key_is_numbas_type(value):
    """The run-time key of an argument is exactly the key of numba's own type for it (else a wrong AOT entry
    would read memory as the wrong type)."""
    import numba

    assert _jit._call_key((value,)) == _jit._fast_key((_jit._numba_key(numba.typeof(value)),))


def test_unsupported_arguments_go_to_numba():
    assert _jit._call_key((np.zeros(3), None)) is None
    assert _jit._call_key((np.zeros(3), (1, 2))) is None
    assert _jit._call_key((2**70,)) is None
    assert _jit._call_key((np.zeros(3, dtype=np.complex128),)) is None


_CHILD = r"""
import json, sys
import numpy as np
from startrack._kernels import _jit
from startrack._kernels.attitude import quat_to_dcm
q = np.array([0.1, -0.2, 0.3, 0.9]); q /= np.linalg.norm(q)
out = {"aot": _jit.aot_loaded(), "dcm": quat_to_dcm(q).tolist(), "numba_after_aot_call": "numba" in sys.modules}
# Each returned array's Python type is unpickled once, not per call (numba.pycc's boxing kept one more reference to
# numpy.ndarray at every return).
refs = sys.getrefcount(np.ndarray)
for _ in range(1000):
    quat_to_dcm(q)
out["ndarray_refs_per_1000_calls"] = sys.getrefcount(np.ndarray) - refs
# float32 has no AOT entry: numba compiles it (a wrong-type AOT call would crash or give garbage)
out["dcm32"] = quat_to_dcm(q.astype(np.float32)).tolist()
out["numba_after_fallback"] = "numba" in sys.modules
print(json.dumps(out))
"""


def test_aot_build_runs_without_numba_and_falls_back_exactly(tmp_path):
    env = dict(os.environ, STARTRACK_KERNELS=str(tmp_path), STARTRACK_AOT="1")
    build = ("import numpy as np; from startrack._kernels import _jit; "
             "from startrack._kernels.attitude import quat_to_dcm; "
             "quat_to_dcm(np.array([0.0, 0.0, 0.0, 1.0])); "
             "print(_jit.build_aot(kernels=[k for k in _jit._KERNELS if k.qualname == 'attitude.quat_to_dcm']))")
    proc = subprocess.run([sys.executable, "-c", build], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert "1)" in proc.stdout
    manifest = json.loads(next(tmp_path.glob("kernels-*.json")).read_text())
    assert list(manifest["kernels"]) == ["attitude.quat_to_dcm"]
    from llvmlite import binding

    assert manifest["cpu"] == binding.get_host_cpu_name()     # built for this CPU (pycc's default is generic)

    child = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True, timeout=600)
    assert child.returncode == 0, child.stderr
    out = json.loads(child.stdout)
    assert out["aot"] and not out["numba_after_aot_call"] and out["numba_after_fallback"]
    assert abs(out["ndarray_refs_per_1000_calls"]) < 10
    from startrack.rotations import quaternion_to_dcm

    q = np.array([0.1, -0.2, 0.3, 0.9])
    q /= np.linalg.norm(q)
    np.testing.assert_allclose(out["dcm"], quaternion_to_dcm(q), atol=1e-15)
    np.testing.assert_allclose(out["dcm32"], quaternion_to_dcm(q), atol=1e-6)

    # Another version of the code (a different tag) misses the build: numba, same numbers.
    off = subprocess.run([sys.executable, "-c", _CHILD], env=dict(env, STARTRACK_AOT="0"), capture_output=True,
                         text=True, timeout=600)
    assert off.returncode == 0, off.stderr
    assert not json.loads(off.stdout)["aot"]
    assert json.loads(off.stdout)["dcm"] == out["dcm"]

    # A damaged build (4 KB overwritten inside its machine code) is not loaded: its checksum fails (issue 41; on
    # main the library was loaded and run), said once on stderr, and numba's kernels give the same numbers.
    lib = next(tmp_path.glob("kernels-*.so"))
    assert len(manifest["sha256"]) == 64
    assert (tmp_path / (lib.name[:-3] + ".checked")).exists()      # the first load hashed it and stamped it
    data = bytearray(lib.read_bytes())
    data[len(data) // 2: len(data) // 2 + 4096] = os.urandom(4096)
    lib.write_bytes(bytes(data))
    bad = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True, timeout=600)
    assert bad.returncode == 0, bad.stderr
    assert not json.loads(bad.stdout)["aot"] and json.loads(bad.stdout)["dcm"] == out["dcm"]
    assert bad.stderr.count("sha256: does not match") == 1 and lib.name in bad.stderr


def test_every_kernel_module_declares_lazy_kernels():
    """A kernel module that took njit from numba would hand numba a lazy kernel it cannot type."""
    here = os.path.dirname(_jit.__file__)
    for name in sorted(os.listdir(here)):
        if name.endswith(".py") and name != "_jit.py":
            text = open(os.path.join(here, name)).read()
            assert "from numba import" not in text and "import numba" not in text, name


def test_clearing_another_cache_keeps_the_compiled_kernels(tmp_path):
    from conftest import run_cli

    kernels = tmp_path / "kernels"
    kernels.mkdir()
    (kernels / "kernels-abc.so").write_bytes(b"x")
    other = tmp_path / "other"
    other.mkdir()
    (other / "patterns-old.idx").write_bytes(b"x")
    env = {"STARTRACK_CACHE": str(other), "STARTRACK_KERNELS": str(kernels)}
    run_cli("cache", "clear", env=env, check=True)
    assert not list(other.iterdir()) and (kernels / "kernels-abc.so").exists()
    inside = {"STARTRACK_CACHE": str(tmp_path), "STARTRACK_KERNELS": str(kernels)}
    run_cli("cache", "clear", env=inside, check=True)
    assert not (kernels / "kernels-abc.so").exists()


def test_numba_version_is_read_without_importing_it():
    """The AOT build's tag names numba's version as importlib.metadata does, without importing either."""
    import subprocess
    import sys
    from importlib.metadata import version

    from startrack._kernels._jit import _numba_version

    assert _numba_version() == version("numba")
    code = ("import sys; from startrack._kernels._jit import _numba_version; _numba_version(); "
            "print('numba' in sys.modules, 'importlib.metadata' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False"]


def test_the_build_tag_covers_every_warm_up():
    """The AOT build's tag hashes the sources of the warm-ups that decide its entries: a warm-up moved to a module
    the tag does not read would let a change of it keep a stale build (its new argument types then compiled by
    numba inside a frame's time)."""
    import ast
    import inspect
    import os

    import startrack
    from startrack import solve
    from startrack._kernels import _jit

    package = os.path.dirname(os.path.abspath(startrack.__file__))
    tree = ast.parse(inspect.getsource(solve.warm_for_build))
    called = {node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id
              for node in ast.walk(tree) if isinstance(node, ast.Call)
              and isinstance(node.func, (ast.Name, ast.Attribute))}
    warm_ups = {name for name in called if name.startswith("warm")}
    assert {"warm_up", "warm_bands"} <= warm_ups, warm_ups
    from startrack import centroid, identify, patterns
    from startrack.identify import catalog_match

    modules = {"warm_up": identify, "warm_bands": centroid, "warm_kernels": patterns,
               "warm_final_match": catalog_match}
    for fn in [solve.warm_for_build, solve._warm, identify.warm_up] + [getattr(m, n) for n, m in modules.items()]:
        rel = os.path.relpath(inspect.getsourcefile(fn), package).replace(os.sep, "/")
        assert rel in _jit._WARM_UP_SOURCES, (fn.__qualname__, rel)


def test_a_nested_call_compiles_its_callee_once_for_literal_and_counted_arguments():
    """numba typed a call between kernels with its literal arguments' types (``f(a, 0)``; a counter ``k = 0 ...
    k += 1`` still ``Literal[int](0)`` in type inference's first pass) and compiled the callee again for each: a
    first solve compiled refine_from, _sort_indices and _sort_small twice.  One int64 specialization serves
    every call, with the same values."""
    from numba.core import types

    @_jit.njit(cache=False)
    def head_sum(a, n):
        return a[:n].sum()

    @_jit.njit(cache=False)
    def literal_calls(a):
        return head_sum(a, 0) + head_sum(a, 2) + head_sum(a, a.shape[0])

    @_jit.njit(cache=False)
    def counted_call(a):
        k = 0
        for i in range(a.shape[0]):
            if a[i] > 0.5:
                k += 1
        return head_sum(a, k)

    a = np.array([0.0, 1.0, 2.0, 0.25, 3.0])
    assert literal_calls(a) == 0.0 + 1.0 + a.sum()
    assert counted_call(a) == a[:3].sum()
    sigs = head_sum.dispatcher.signatures
    assert len(sigs) == 1, sigs
    assert sigs[0][1] == types.int64
