"""Provenance: which code, libraries and CPU produced a result.

Model cards, reports, cell caches and Rerun recordings carry these facts, so a number can be traced
to what made it and a cache can never serve a result computed by other code or another policy.

>>> library_versions()["mujoco"]  # doctest: +SKIP
'3.17.0'
>>> len(code_version())
16
"""

from __future__ import annotations

import functools
import hashlib
import os
import platform
import subprocess
from pathlib import Path

from cefc_mj import paths
from cefc_mj.version import __version__

_PACKAGE_DIR = Path(__file__).resolve().parent


@functools.lru_cache(maxsize=None)
def code_version() -> str:
    """A digest (16 hex digits) of every Python source file of the package, by path and content.

    Unlike a git commit it exists in an installed wheel too, and it changes with uncommitted edits,
    so a cache keyed on it is never served by other code.
    """
    digest = hashlib.sha256()
    for source in sorted(_PACKAGE_DIR.rglob("*.py")):
        digest.update(source.relative_to(_PACKAGE_DIR).as_posix().encode())
        digest.update(b"\0")
        digest.update(source.read_bytes())
        digest.update(b"\0")
    return digest.hexdigest()[:16]


def display_path(path: str | os.PathLike) -> str:
    """A path as reports and model cards record it: relative to the project root when inside it
    ('policies/atm_c6_step3.pt'), else relative to the working folder when inside that ('runs/x'), else
    absolute (a folder of the user's that no relative path names)."""
    path = Path(path).resolve()
    for base in (paths.PROJECT_ROOT, Path.cwd()):
        try:
            return path.relative_to(base.resolve()).as_posix()
        except ValueError:
            continue
    return str(path)


def display_run_path(path: str | os.PathLike) -> str:
    """A run folder as shipped reports record it: `display_path`, or, outside the checkout and the
    working folder, its last three components (as `cefc-train --out runs/hl` names it), never an
    absolute path."""
    text = display_path(path)
    return text if not text.startswith("/") else Path(*Path(path).resolve().parts[-3:]).as_posix()


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes (hex); memoized on (path, size, mtime), so a replaced file is re-read."""
    st = os.stat(path)
    return _sha256_of(str(Path(path).resolve()), st.st_size, st.st_mtime_ns)


@functools.lru_cache(maxsize=256)
def _sha256_of(path: str, size: int, mtime_ns: int) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@functools.lru_cache(maxsize=None)
def cpu_model() -> str:
    """The CPU's model name (Linux /proc/cpuinfo, else platform), with the core count."""
    name = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{name or platform.processor() or platform.machine()}, {os.cpu_count()} CPUs"


@functools.lru_cache(maxsize=None)
def library_versions() -> dict[str, str]:
    """Versions of everything that changes a closed-loop number, plus the CPU (see docs/reproduce.md)."""
    import mujoco
    import numba
    import numpy
    import torch

    return {
        "cefc_mj": __version__,
        "code_version": code_version(),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "numba": numba.__version__,
        "mujoco": mujoco.__version__,
        "torch": torch.__version__,
        "cpu": cpu_model(),
        "mkl_cbwr": os.environ.get("MKL_CBWR", ""),
    }


@functools.lru_cache(maxsize=None)
def git_commit() -> str | None:
    """The checkout's HEAD commit (read-only query), or None outside a repository (an installed wheel)."""
    if paths.CHECKOUT_ROOT is None:
        return None
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=paths.CHECKOUT_ROOT, capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def version_line(prog: str) -> str:
    """What `--version` prints: the package version, code digest and the key libraries."""
    v = library_versions()
    return (
        f"{prog} {v['cefc_mj']} (code {v['code_version']}); python {v['python']}, numpy {v['numpy']}, "
        f"numba {v['numba']}, mujoco {v['mujoco']}, torch {v['torch']}"
    )
