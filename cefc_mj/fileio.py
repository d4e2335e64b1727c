"""Atomic file writes: a temp file next to the target, then a rename, so a kill never leaves a torn file."""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

from cefc_mj.errors import ConfigError


def current_umask() -> int:
    """The process umask (read from /proc on Linux; elsewhere set and restored at once)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Call `write(file_object)` on a temp file next to `path`, then rename it onto `path`.
    The folder must exist (ConfigError otherwise).

    The file gets the mode a plain `open(path, "w")` would give it: the existing file's mode when
    one is replaced, else 0o666 less the umask (mkstemp alone would leave it private, 0o600).
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise ConfigError(f"{path}: folder {path.parent} does not exist")
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
    except FileNotFoundError:
        mode = 0o666 & ~current_umask()
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            os.fchmod(fh.fileno(), mode)
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def can_write_in(folder: Path) -> bool:
    """Whether a file can be created in the existing `folder`: permissions, then a real probe (root
    passes every permission check, yet cannot write into /proc or a read-only mount)."""
    if not os.access(folder, os.W_OK | os.X_OK):
        return False
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".write-probe-")
    except OSError:
        return False
    os.close(fd)
    os.unlink(probe)
    return True


def make_writable_folder(path: Path) -> None:
    """Create the folder `path` (and its parents) and check that a file can be written in it
    (`can_write_in`); a ConfigError says why not."""
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"cannot write there ({e.strerror or e})") from None
    if not can_write_in(path):
        raise ConfigError("cannot write there (a probe file could not be created)")


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write bytes or text to `path` atomically, creating its folder if needed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda fh: fh.write(data.encode() if isinstance(data, str) else data))
