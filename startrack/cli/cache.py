"""startrack cache: list, build and clear the cached star index and databases."""
import click

from startrack.cli.options import handle_errors, quiet_option


@click.command("cache", short_help="List, build or clear the cached star index and databases.")
@click.argument("action", type=click.Choice(["list", "build", "clear"]), default="list")
@click.option("--catalog", type=click.Choice(["hipparcos", "gaia"]), default="hipparcos", show_default=True,
              help="build: the index of this catalog (gaia: the deep index of 0.8-3 deg fields, ~280 MB, about a "
                   "minute; the extra startrack[gaia]).")
@quiet_option
@handle_errors
def command(action, catalog, quiet):
    """List, build or clear the cache of `startrack solve`.

    The blind solver's star pattern index (one memory-mapped file, built from
    the shipped catalog), a decompressed copy of the shipped catalog and the
    k-vector and label databases of the older solvers are cached in
    $STARTRACK_CACHE, else $XDG_CACHE_HOME/startrack, else ~/.cache/startrack.  `build` makes the default pattern index now and
    compiles the solver's kernels ahead of time (into $STARTRACK_KERNELS, else
    the default cache's kernels/ folder: one build serves every cache), so
    that `solve` neither waits nor loads numba (`build --catalog gaia`: the
    deep index of narrow fields, which `solve` otherwise builds when a frame
    first needs it); `clear` deletes every cached
    file (the compiled kernels too when they are inside the cache cleared).

    \b
    Example (what is cached, and its size):
      startrack cache list
    \b
    Example (build once, e.g. in a Dockerfile or after installing):
      startrack cache build
    \b
    Example (start afresh):
      startrack cache clear
    """
    import glob
    import os
    import time

    from startrack.patterns import cache_dir

    root = cache_dir()
    files = sorted(p for p in glob.glob(os.path.join(root, "*")) if os.path.isfile(p))
    if action == "list":
        total = 0
        for p in files:
            size = os.path.getsize(p)
            total += size
            click.echo(f"{size / 1e6:9.1f} MB  {os.path.basename(p)}")
        click.echo(f"{total / 1e6:9.1f} MB  in {root} ({len(files)} file(s))")
    elif action == "build":
        from startrack.patterns import default_index_path
        from startrack.solve import _process_index

        kind = "deep" if catalog == "gaia" else "default"
        t0 = time.perf_counter()
        existed = os.path.exists(default_index_path(kind=kind))
        index = _process_index(kind)
        from startrack.catalog import load_catalog

        load_catalog()      # the shipped catalog's cached copy (a command then reads it without h5py)
        if not quiet:
            verb = "opened" if existed else "built"
            click.echo(f"cache: {verb} {index.path} ({index.size_bytes / 1e6:.1f} MB, "
                       f"{len(index.keys):,} patterns) in {time.perf_counter() - t0:.1f} s", err=True)
        _build_kernels(quiet, index)
    else:
        from startrack._kernels._jit import kernels_dir

        # The compiled kernels go with the cache only where they live inside it (the
        # default layout): clearing another $STARTRACK_CACHE leaves them alone.
        kdir = os.path.realpath(kernels_dir())
        inside = os.path.commonpath([kdir, os.path.realpath(root)]) == os.path.realpath(root)
        kernels = sorted(glob.glob(os.path.join(kdir, "kernels-*"))) if inside else []
        for p in files + kernels:
            os.remove(p)
        if not quiet:
            click.echo(f"cache: removed {len(files) + len(kernels)} file(s) from {root}"
                       + (f" and {kdir}" if kernels else ""), err=True)


def _build_kernels(quiet: bool, index) -> None:
    """The ahead-of-time build of the solver's kernels (start-up without numba), once per code version."""
    import os
    import sys
    import time

    from startrack._kernels._jit import aot_intact, aot_path, build_aot
    from startrack.formats.hdf5 import build_lock

    path = aot_path()
    if os.environ.get("STARTRACK_AOT", "1") == "0" or aot_intact(path):
        return
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with build_lock(path):
        if aot_intact(path):
            return
        # Always visible, like the index's notice: a minute of silence looks like a hang.
        sys.stderr.write(f"startrack: compiling the solver's kernels ahead of time once, 1-2 min, into "
                         f"{os.path.dirname(path)}\n")
        sys.stderr.flush()
        t0 = time.perf_counter()
        from startrack.solve import warm_for_build

        warm_for_build(index)
        try:
            path, n = build_aot()
        except Exception as exc:  # noqa: BLE001 - no C compiler, an unsupported platform: numba's JIT remains
            sys.stderr.write(f"startrack: kernels not compiled ahead of time ({type(exc).__name__}: "
                             f"{str(exc).splitlines()[0][:200] if str(exc) else ''}); commands use numba's "
                             f"just-in-time kernels instead\n")
            return
        if not quiet:
            click.echo(f"cache: built {path} ({n} kernel entry points) in {time.perf_counter() - t0:.1f} s",
                       err=True)
