"""Where the project's top-level artifact folders live.

`assets/`, `controllers/`, `policies/` and `eval/` are top-level folders of the repository that users
read and swap. The package finds them, in this order:

1. `CEFC_MJ_HOME`, when set: a folder holding your own copy of all four (see `python -m cefc_mj.paths`);
2. the checkout the package runs from (a clone, or the editable install the README uses);
3. the copy a wheel carries inside the package, `cefc_mj/_shipped/` (pyproject.toml maps the top-level
   folders there; the generated `eval/reports/` is not shipped).

The installed copy is read-only data: code that writes (reports, trained policies) should not default
to a folder under `PROJECT_ROOT` when `DATA_SOURCE == "installed"`.

    python -m cefc_mj.paths        # prints where each folder was found
"""

from __future__ import annotations

import os
from pathlib import Path

_PACKAGE_DIR = Path(__file__).resolve().parent
SHIPPED_DIR = _PACKAGE_DIR / "_shipped"
"""The data a wheel install carries (absent in a checkout, where the top-level folders are used)."""


def _checkout_root() -> Path | None:
    """The repository the package runs from, or None when it runs from site-packages.

    A checkout has pyproject.toml and assets/ beside the package; site-packages has neither.
    """
    root = _PACKAGE_DIR.parent
    return root if (root / "pyproject.toml").is_file() and (root / "assets").is_dir() else None


CHECKOUT_ROOT = _checkout_root()
"""The repository the package runs from (for git queries), or None for a wheel install."""

if os.environ.get("CEFC_MJ_HOME"):
    PROJECT_ROOT, DATA_SOURCE = Path(os.environ["CEFC_MJ_HOME"]).expanduser(), "CEFC_MJ_HOME"
elif CHECKOUT_ROOT is not None:
    PROJECT_ROOT, DATA_SOURCE = CHECKOUT_ROOT, "checkout"
else:
    PROJECT_ROOT, DATA_SOURCE = SHIPPED_DIR, "installed"
# DATA_SOURCE says which of the three PROJECT_ROOT is: "CEFC_MJ_HOME", "checkout" or "installed".

ASSETS_DIR = PROJECT_ROOT / "assets"
MJCF_DIR = ASSETS_DIR / "mjcf"
CONTROLLERS_DIR = PROJECT_ROOT / "controllers"
POLICIES_DIR = PROJECT_ROOT / "policies"
EVAL_DIR = PROJECT_ROOT / "eval"


def main() -> None:
    """Print where the data folders were found, one `name: path` per line."""
    print(f"source: {DATA_SOURCE}")
    print(f"root: {PROJECT_ROOT}")
    for name, folder in (
        ("assets", ASSETS_DIR),
        ("controllers", CONTROLLERS_DIR),
        ("policies", POLICIES_DIR),
        ("eval", EVAL_DIR),
    ):
        print(f"{name}: {folder}{'' if folder.is_dir() else '  (missing)'}")


if __name__ == "__main__":
    main()
