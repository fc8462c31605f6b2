"""Where startrack keeps what it builds once and reads afterwards (pattern indexes, the shipped catalog's decompressed
copy): a module of its own so that every layer can name the place without importing the others."""
import os

__all__ = ["cache_dir"]


def cache_dir() -> str:
    """``$STARTRACK_CACHE``, else ``$XDG_CACHE_HOME/startrack``, else ``~/.cache/startrack`` (created)."""
    path = os.environ.get("STARTRACK_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "startrack")
    os.makedirs(path, exist_ok=True)
    return path
