"""startrack cache: list, build and clear the cached star index and databases."""
import click

from startrack.cli.options import handle_errors, quiet_option


@click.command("cache", short_help="List, build or clear the cached star index and databases.")
@click.argument("action", type=click.Choice(["list", "build", "clear"]), default="list")
@quiet_option
@handle_errors
def command(action, quiet):
    """List, build or clear the cache of `startrack solve`.

    The blind solver's star pattern index (one memory-mapped file, built from
    the shipped catalog) and the k-vector and label databases of the older
    solvers are cached in $STARTRACK_CACHE, else $XDG_CACHE_HOME/startrack,
    else ~/.cache/startrack.  `build` makes the default pattern index now (and
    compiles the solver's kernels), so that the first `solve` does not wait;
    `clear` deletes every cached file.

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

        t0 = time.perf_counter()
        existed = os.path.exists(default_index_path())
        index = _process_index()
        if not quiet:
            verb = "opened" if existed else "built"
            click.echo(f"cache: {verb} {index.path} ({index.size_bytes / 1e6:.1f} MB, "
                       f"{len(index.keys):,} patterns) in {time.perf_counter() - t0:.1f} s", err=True)
    else:
        for p in files:
            os.remove(p)
        if not quiet:
            click.echo(f"cache: removed {len(files)} file(s) from {root}", err=True)
