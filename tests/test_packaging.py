"""Packaging: the sdist and wheel carry the data the code reads at run time, and an installed wheel
finds it and flies.

Builds run on a copy of the checkout in tmp (a build writes build/ and *.egg-info into its source
tree) through the setuptools backend of the running interpreter, without build isolation (no
network). The installed checks use a fresh venv outside the checkout that sees the heavy
dependencies (torch, mujoco, ...) of the running interpreter through a .pth file, so the only
cefc_mj it can import is the installed wheel.
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import sysconfig
import tarfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHIPPED = "cefc_mj/_shipped"
NOT_COPIED = shutil.ignore_patterns(".git", ".venv", "venv", "build", "dist", "*.egg-info", ".pytest_cache", "runs")
BUILD_ARTIFACTS = ("build", "dist", "cefc_mj.egg-info", "cefc_mj/_shipped")
"""What a build in the checkout would create or touch; the tests must leave them as they were."""


def _run(cmd: list, cwd: Path, timeout: float = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    out = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, f"{cmd} failed ({out.returncode}):\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    return out


def _build(hook: str, source: Path, out_dir: Path) -> Path:
    """Run the PEP 517 hook ("build_sdist" or "build_wheel") in `source`; the built file."""
    script = f"import sys; from setuptools import build_meta; print(build_meta.{hook}(sys.argv[1]))"
    out = _run([sys.executable, "-c", script, out_dir], cwd=source)
    return out_dir / out.stdout.strip().splitlines()[-1]


def _artifact_state() -> dict[str, int | None]:
    return {name: (REPO / name).stat().st_mtime_ns if (REPO / name).exists() else None for name in BUILD_ARTIFACTS}


def _shipped_data() -> set[str]:
    """The wheel paths of the checkout's data the code reads at run time (not eval/reports/)."""
    files = [
        *(REPO / "assets" / "mjcf").glob("*.xml"),
        *(REPO / "controllers").glob("*.params"),
        *(REPO / "policies").glob("*.pt"),
        *(REPO / "policies").glob("*.json"),
        REPO / "eval" / "paper_tables.json",
        REPO / "eval" / "table8_bands.json",
    ]
    return {f"{SHIPPED}/{f.relative_to(REPO).as_posix()}" for f in files}


@dataclass
class Built:
    sdist: Path
    wheel: Path
    wheel_from_sdist: Path
    artifacts_before: dict
    artifacts_after: dict


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Built:
    """sdist and wheel of a copy of the checkout (what `pip install git+...` builds), and the wheel built
    from the unpacked sdist (what `python -m build` makes)."""
    tmp = tmp_path_factory.mktemp("build")
    before = _artifact_state()
    shutil.copytree(REPO, tmp / "src", ignore=NOT_COPIED)
    sdist = _build("build_sdist", tmp / "src", tmp / "dist")
    wheel = _build("build_wheel", tmp / "src", tmp / "dist")
    with tarfile.open(sdist) as tar:  # the "data" filter exists from Python 3.11.4 on
        tar.extractall(tmp / "unpacked", **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
    wheel_from_sdist = _build("build_wheel", next((tmp / "unpacked").iterdir()), tmp / "dist-from-sdist")
    return Built(sdist, wheel, wheel_from_sdist, before, _artifact_state())


@pytest.fixture(scope="module")
def venv(built, tmp_path_factory) -> Path:
    """A fresh venv outside the checkout with the wheel installed (no deps: those come via a .pth)."""
    root = tmp_path_factory.mktemp("venv") / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", root], cwd=root.parent)
    python = root / "bin" / "python"
    purelib = Path(
        _run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], cwd=root.parent).stdout.strip()
    )
    # the running interpreter's site-packages, after the venv's own: torch etc. without a second copy
    deps = [p for p in site.getsitepackages() if Path(p).is_dir()] or [sysconfig.get_path("purelib")]
    (purelib / "_cefc_test_deps.pth").write_text("\n".join(deps) + "\n")
    _run(
        [sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", "-q", built.wheel],
        cwd=root.parent,
    )
    return root


def _clean_env() -> dict[str, str]:
    """The environment without anything that would point the child at the checkout."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "CEFC_MJ_HOME", "VIRTUAL_ENV")}


def _purelib(venv: Path) -> Path:
    return Path(
        _run(
            [venv / "bin" / "python", "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], cwd=venv
        ).stdout.strip()
    ).resolve()


# ---------------------------------------------------------------------------- fast: file lists
def test_wheel_carries_code_and_runtime_data_only(built):
    names = set(zipfile.ZipFile(built.wheel).namelist())
    missing_data = _shipped_data() - names
    assert not missing_data, f"data missing from the wheel: {sorted(missing_data)}"
    # every module of the package (a subpackage left out of pyproject's explicit list shows up here)
    sources = {p.relative_to(REPO).as_posix() for p in (REPO / "cefc_mj").rglob("*.py") if "__pycache__" not in p.parts}
    assert not sources - names, f"modules missing from the wheel: {sorted(sources - names)}"
    assert not [n for n in names if "/reports/" in n], "generated eval/reports/ must not ship"
    assert not [n for n in names if n.endswith((".pyc", ".nbi", ".nbc"))], "caches must not ship"
    assert not [n for n in names if not n.startswith(("cefc_mj/", "cefc_mj-"))], "only the cefc_mj package installs"
    meta = zipfile.ZipFile(built.wheel).read("cefc_mj-0.1.0.dist-info/METADATA").decode()
    assert "License-Expression: MIT" in meta
    assert "cefc_mj-0.1.0.dist-info/licenses/LICENSE" in names
    scripts = zipfile.ZipFile(built.wheel).read("cefc_mj-0.1.0.dist-info/entry_points.txt").decode()
    assert "cefc-eval = cefc_mj.cli.eval:main" in scripts and "cefc-train = cefc_mj.cli.train:main" in scripts
    assert "cefc-view = cefc_mj.cli.view:main" in scripts
    # dm-control is the `dm-control` extra (and in `test`), not a dependency of the core
    requires = [line for line in meta.splitlines() if line.startswith("Requires-Dist: dm-control")]
    assert requires and all("extra ==" in line for line in requires), requires
    assert {'extra == "dm-control"', 'extra == "test"'} <= {line.split("; ")[-1] for line in requires}, requires


def test_wheel_from_sdist_matches_wheel_from_tree(built):
    """MANIFEST.in is complete: `python -m build` (sdist -> wheel) ships what a tree build does."""
    tree = set(zipfile.ZipFile(built.wheel).namelist())
    via_sdist = set(zipfile.ZipFile(built.wheel_from_sdist).namelist())
    assert tree == via_sdist, (
        f"only from the tree: {sorted(tree - via_sdist)}; only via sdist: {sorted(via_sdist - tree)}"
    )


def test_sdist_carries_the_top_level_data_folders(built):
    with tarfile.open(built.sdist) as tar:
        names = {n.split("/", 1)[1] for n in tar.getnames() if "/" in n}
    expected = {n.removeprefix(f"{SHIPPED}/") for n in _shipped_data()}
    expected |= {"LICENSE", "CITATION.cff", "README.md", "pyproject.toml", "MANIFEST.in", "tests/test_packaging.py"}
    assert not expected - names, f"missing from the sdist: {sorted(expected - names)}"
    assert not [n for n in names if n.startswith("eval/reports")], "generated eval/reports/ must not ship"


def test_builds_leave_the_checkout_alone(built):
    assert built.artifacts_after == built.artifacts_before


# ---------------------------------------------------------------------------- fast: an installed wheel
def test_installed_wheel_finds_its_data_outside_the_checkout(venv, tmp_path):
    """From a folder outside any checkout, the package and its data come from the venv."""
    script = (
        "import json, cefc_mj, cefc_mj.paths as p\n"
        "from cefc_mj.control.airframe import load_airframe\n"
        "from cefc_mj.control.params import load_params\n"
        "from cefc_mj.nn.policy_io import load_policy\n"
        "from cefc_mj.eval.table8 import paper_table8\n"
        "from cefc_mj.eval.bands import load_bands\n"
        "print(json.dumps({'package': cefc_mj.__file__, 'source': p.DATA_SOURCE, 'policies': str(p.POLICIES_DIR),\n"
        "    'checkout': p.CHECKOUT_ROOT, 'mass': load_airframe('iris').mass, 'gains': len(load_params('iris')),\n"
        "    'obs_dim': load_policy('atm_c5_step3').obs_dim, 'paper': bool(paper_table8()), "
        "'bands': bool(load_bands())}))\n"
    )
    out = json.loads(_run([venv / "bin" / "python", "-c", script], cwd=tmp_path, env=_clean_env()).stdout)
    purelib = _purelib(venv)
    assert Path(out["package"]).resolve().is_relative_to(purelib)
    assert out["source"] == "installed" and out["checkout"] is None
    assert Path(out["policies"]).resolve().is_relative_to(purelib)
    assert out["mass"] > 0 and out["gains"] > 0 and out["obs_dim"] > 0 and out["paper"] and out["bands"]


def test_cefc_mj_home_overrides_the_installed_copy(venv, tmp_path):
    home = tmp_path / "home"
    shutil.copytree(REPO / "policies", home / "policies")
    out = _run(
        [venv / "bin" / "python", "-m", "cefc_mj.paths"], cwd=tmp_path, env={**_clean_env(), "CEFC_MJ_HOME": str(home)}
    ).stdout
    lines = dict(line.split(": ", 1) for line in out.splitlines())
    assert lines["source"] == "CEFC_MJ_HOME" and Path(lines["root"]) == home
    assert lines["policies"] == str(home / "policies")
    assert lines["assets"].endswith("(missing)")  # the whole root is swapped, and a missing folder is named


def test_editable_install_uses_the_checkout_folders(tmp_path):
    """`pip install -e .` (what the README uses) reads the top-level folders of the checkout."""
    src = tmp_path / "checkout"
    shutil.copytree(REPO, src, ignore=NOT_COPIED)
    root = tmp_path / "venv-e"
    _run([sys.executable, "-m", "venv", "--without-pip", root], cwd=tmp_path)
    purelib = Path(
        _run(
            [root / "bin" / "python", "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], cwd=tmp_path
        ).stdout.strip()
    )
    (purelib / "_cefc_test_deps.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    _run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            root / "bin" / "python",
            "install",
            "--no-deps",
            "--no-index",
            "--no-build-isolation",
            "-q",
            "-e",
            src,
        ],
        cwd=tmp_path,
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = _run(
        [root / "bin" / "python", "-c", "import cefc_mj.paths as p; print(p.DATA_SOURCE, p.POLICIES_DIR)"],
        cwd=elsewhere,
        env=_clean_env(),
    ).stdout.split()
    assert out == ["checkout", str(src / "policies")]


# ---------------------------------------------------------------------------- slow: an installed wheel flies
@pytest.mark.slow
def test_installed_wheel_flies_an_episode_and_the_cli(venv, tmp_path):
    """A MuJoCo episode and `cefc-eval` from the installed console script (numba compiles afresh in the
    new venv: ~30-60 s)."""
    script = (
        "import json, numpy as np, cefc_mj\n"
        "from cefc_mj.eval.runner import EpisodeSpec, run_episode\n"
        "r = run_episode(EpisodeSpec(formation=5, seed=0, steps=20), record=True)\n"
        "pos = r.record.agent_pos\n"
        "print(json.dumps({'package': cefc_mj.__file__, 'F': r.F, 'N': r.N, 'C': r.C, 'steps': r.steps,\n"
        "    'diverged': r.diverged, 'altitude': float(pos[-1, :, 2].mean()),\n"
        "    'moved': float(np.linalg.norm(pos[-1, :, :2] - pos[0, :, :2], axis=-1).max()),\n"
        "    'airframe_parts': len(r.record.airframe_parts)}))\n"
    )
    out = json.loads(
        _run([venv / "bin" / "python", "-c", script], cwd=tmp_path, env=_clean_env(), timeout=600).stdout.splitlines()[
            -1
        ]
    )
    assert Path(out["package"]).resolve().is_relative_to(_purelib(venv))
    assert out["steps"] == 20 and out["diverged"] is None
    assert 0 <= out["F"] <= 20 and 0 <= out["N"] <= 20 and 0 <= out["C"] <= 100
    assert abs(out["altitude"] - 2.0) < 0.5, "the quadrotors hold the flight altitude"
    assert out["moved"] > 0.01, "the policy moves the quadrotors"
    assert out["airframe_parts"] > 0, "the record drew the airframe from the shipped MJCF"

    result = _run(
        [
            venv / "bin" / "cefc-eval",
            "--steps",
            "10",
            "--formation",
            "5",
            "--episodes",
            "1",
            "--json",
            tmp_path / "r.json",
        ],
        cwd=tmp_path,
        env=_clean_env(),
        timeout=600,
    )
    episode = json.loads((tmp_path / "r.json").read_text())["rows"]["5"]["SITL-S"]["episodes_detail"][0]
    assert episode["steps"] == 10 and episode["diverged"] is None
    row = next(line for line in result.stdout.splitlines() if line.split()[:1] == ["5"])
    assert "-" not in row.split(), f"the paper's reference (eval/paper_tables.json) is missing: {row!r}"
