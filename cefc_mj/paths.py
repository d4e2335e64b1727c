"""Where the project's top-level artifact folders live.

`assets/`, `controllers/`, `policies/` and `eval/` are top-level folders that users read and swap
(DESIGN §2). They are found next to the package (a checkout or an editable install, which is what the
README installs); set `CEFC_MJ_HOME` to point at another copy of them.
"""

import os
from pathlib import Path

PROJECT_ROOT = Path(os.environ.get("CEFC_MJ_HOME", Path(__file__).resolve().parent.parent))
ASSETS_DIR = PROJECT_ROOT / "assets"
MJCF_DIR = ASSETS_DIR / "mjcf"
CONTROLLERS_DIR = PROJECT_ROOT / "controllers"
POLICIES_DIR = PROJECT_ROOT / "policies"
EVAL_DIR = PROJECT_ROOT / "eval"
