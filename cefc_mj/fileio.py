"""Atomic file writes: a temp file next to the target, then a rename, so a kill never leaves a torn file."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

from cefc_mj.errors import ConfigError


def atomic_write(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Call `write(file_object)` on a temp file next to `path`, then rename it onto `path`.
    The folder must exist (ConfigError otherwise)."""
    path = Path(path)
    if not path.parent.is_dir():
        raise ConfigError(f"{path}: folder {path.parent} does not exist")
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write bytes or text to `path` atomically, creating its folder if needed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda fh: fh.write(data.encode() if isinstance(data, str) else data))
