"""numba set-up shared by the compiled kernels: an on-disk cache that works wherever the package lies,
and one line on stderr when a cold cache means the kernels are about to be compiled.

Compiling every kernel takes about 20 s; with `cache=True` numba keeps the machine code on disk and
later processes load it in about a second. Where numba puts it, first writable wins:

1. `NUMBA_CACHE_DIR`, when the user sets it;
2. `__pycache__/` beside the source file (a checkout, or a package installed into a writable venv);
3. the user's cache folder, `~/.cache/numba/` (or `$XDG_CACHE_HOME/numba/`; a read-only system install);
4. `<temp dir>/cefc-mj-numba-<uid>/`, set here when none of the above is writable (numba itself
   would refuse to import a `cache=True` function).

The cache is keyed on the source's content hash, the CPU and the numba version, so an edit or an
upgrade recompiles on its own; the loaded code is the code numba would compile (results are
bit-identical, `tests/test_startup.py`). Kernels are declared as with numba, in a module file
(the cache is keyed on it):

    from cefc_mj.jit import njit

    @njit
    def kernel(pos, out): ...

    @njit(inline="always")
    def helper(x): ...
"""

from __future__ import annotations

import functools
import os
import sys
import tempfile

import numba
from numba.core import event
from numba.core.caching import FunctionCache

COMPILE_NOTICE = "cefc-mj: compiling numba kernels (first run only, ~20 s)..."


def njit(func=None, **options):
    """`numba.njit` with the disk cache on; `@njit` or `@njit(inline="always")` like numba's."""
    if func is None:
        return functools.partial(njit, **options)
    return numba.njit(cache=True, **options)(func)


def _cache_probe():  # a function in this package for numba's cache locators to try
    return None


def ensure_cache_location() -> None:
    """Point numba at `<temp dir>/cefc-mj-numba-<uid>` when it has nowhere else to write its cache.

    numba looks for a writable folder when a `cache=True` function is defined and raises
    RuntimeError if there is none (package and home both read-only, e.g. a locked-down container).
    """
    if numba.config.DISABLE_JIT:
        return
    try:
        FunctionCache(_cache_probe)
    except RuntimeError:
        uid = os.getuid() if hasattr(os, "getuid") else os.getpid()
        numba.config.CACHE_DIR = os.path.join(tempfile.gettempdir(), f"cefc-mj-numba-{uid}")


class _CompileNotice(event.Listener):
    """Prints COMPILE_NOTICE before the first compile of a cefc_mj kernel in this process.

    numba raises the "numba:compile" event only when a signature is neither compiled in this
    process nor found in the disk cache, i.e. exactly when a cold cache costs compile time.
    """

    def __init__(self):
        self.announced = False

    def on_start(self, ev: event.Event) -> None:
        if self.announced:
            return
        py_func = getattr(ev.data.get("dispatcher"), "py_func", None)
        if not getattr(py_func, "__module__", "").startswith("cefc_mj."):
            return
        self.announced = True
        if "tqdm" in sys.modules:  # a running progress bar is cleared and redrawn around the line
            sys.modules["tqdm"].tqdm.write(COMPILE_NOTICE, file=sys.stderr)
        else:
            print(COMPILE_NOTICE, file=sys.stderr, flush=True)

    def on_end(self, ev: event.Event) -> None:
        pass


ensure_cache_location()
compile_notice = _CompileNotice()
event.register("numba:compile", compile_notice)
