"""The ``startrack`` group.  Commands are loaded lazily, by name."""
from __future__ import annotations

import importlib
import sys

import click

from startrack._version import __version__
from startrack.cli.options import verbose_option

# name -> module under startrack.cli; each module defines ``command``.
COMMANDS = {
    "catalog-filter": "catalog_filter",
    "catalog-stats": "catalog_stats",
    "render": "render",
    "centroid": "centroid",
    "build-kvector": "build_kvector",
    "build-labels": "build_labels",
    "build-triangles": "build_triangles",
    "identify": "identify",
    "attitude": "attitude",
    "track": "track",
    "plot": "plot",
    "solve": "solve",
    "calibrate": "calibrate",
    "cache": "cache",
    "evaluate": "evaluate",
}


class LazyGroup(click.Group):
    """A group that imports a command's module only when it is listed or run."""

    def list_commands(self, ctx):  # noqa: ARG002 - click's signature
        return list(COMMANDS)

    def get_command(self, ctx, name):  # noqa: ARG002 - click's signature
        module = COMMANDS.get(name)
        if module is None:
            return None
        return importlib.import_module(f"startrack.cli.{module}").command

    def resolve_command(self, ctx, args):
        name = args[0] if args else ""
        if args and name not in COMMANDS and not name.startswith("-"):
            import difflib

            close = difflib.get_close_matches(name, list(COMMANDS), n=3, cutoff=0.6)
            hint = f" Did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
            raise click.UsageError(f"No such command {name!r}.{hint}", ctx)
        return super().resolve_command(ctx, args)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="startrack")
def cli():
    """startrack: from pictures of the night sky to a spacecraft's attitude.

    Every per-image command reads frame documents (JSON, or JSON Lines for many
    frames) from a file or standard input and writes them to standard output, so
    stages compose in pipes.

    \b
    Example (a database once, then Orion rendered, centroided, identified and solved):
      startrack build-kvector --fov-deg 20 --size 1024x1024 --mag-max 5.5 -o db20.h5
      startrack render --fov-deg 20 --size 1024x1024 --ra 83.8 --dec -1.2 --seed 1 -o orion.png \\
          | startrack centroid | startrack identify -d db20.h5 | startrack attitude > orion.json

    Catalogs and databases are HDF5.  Run `startrack COMMAND --help` for a
    command's options and an example.  `-v` (or `-vv`) before or after the
    command shows log messages on stderr; `-q` hides progress, never errors.

    \b
    Shell completion (bash; zsh and fish alike with zsh_source, fish_source):
      eval "$(_STARTRACK_COMPLETE=bash_source startrack)"
    """


cli.params.append(verbose_option)


def main(argv=None):
    """Entry point: one-line messages and exit 2 for usage errors, no tracebacks."""
    from startrack.cli.options import install_closed_stdout
    from startrack.errors import BadInputError

    install_closed_stdout()
    try:
        rv = cli.main(args=argv, prog_name="startrack", standalone_mode=False)
    except BadInputError as exc:  # output to a closed stdout (--help >&-), outside any command's handler
        click.echo(f"startrack: error: {exc}", err=True)
        sys.exit(exc.exit_code)
    except click.exceptions.UsageError as exc:
        path = exc.ctx.command_path if exc.ctx is not None else "startrack"
        msg = " ".join(exc.format_message().split())
        click.echo(f"{path}: error: {msg} (see '{path} --help')", err=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        click.echo(f"startrack: error: {exc.format_message()}", err=True)
        sys.exit(exc.exit_code)
    except click.exceptions.Abort:
        click.echo("startrack: aborted", err=True)
        sys.exit(1)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)
    if isinstance(rv, int):
        sys.exit(rv)
    sys.exit(0)
