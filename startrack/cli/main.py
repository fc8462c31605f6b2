"""The ``startrack`` group.  Commands are loaded lazily, by name."""
from __future__ import annotations

import importlib
import sys

import click

from startrack._version import __version__

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


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="startrack")
def cli():
    """startrack: from pictures of the night sky to a spacecraft's attitude.

    Every per-image command reads frame documents (JSON, or JSON Lines for many
    frames) from a file or standard input and writes them to standard output, so
    stages compose in pipes:

    \b
      startrack centroid sky.tiff | startrack identify --database db.h5 | startrack attitude

    Catalogs and databases are HDF5.  Run `startrack COMMAND --help` for a
    command's options and an example.
    """


def main(argv=None):
    """Entry point: one-line messages and exit 2 for usage errors, no tracebacks."""
    try:
        rv = cli.main(args=argv, prog_name="startrack", standalone_mode=False)
    except click.exceptions.UsageError as exc:
        path = exc.ctx.command_path if exc.ctx is not None else "startrack"
        click.echo(f"{path}: error: {exc.format_message()} (see '{path} --help')", err=True)
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
