"""Output file names of commands that write one file per frame or image."""
from __future__ import annotations

import os

__all__ = ["numbered_path"]


def numbered_path(path: str, index: int, total: int) -> str:
    """``sky.png`` -> ``sky-0007.png`` when a run writes several files (``total > 1``); else ``path``."""
    if total <= 1:
        return path
    root, ext = os.path.splitext(path)
    return f"{root}-{index:04d}{ext}"
