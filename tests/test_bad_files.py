"""Every file a command reads, made bad in the ways a user or a disk makes it bad, ends in the
project's error type (CefcError) with one line naming the file, and nothing is written.

A seeded fuzz: bad files built from the shipped checkpoints, a freshly written training state, the
iris MJCF, a shipped table8.json and the shipped test ledger (truncated at random offsets, one random
bit flipped) and from other files (empty, text, random bytes, a zip without the expected member, a
pickle with a global the weights-only unpickler refuses, a checkpoint of another network or
formation, a folder), run through every loader: `load_policy`, the adversary loader, the high-level
loader (BenchMARL exports included), `--init-from` and `--resume` (in-process CLI), `--airframe`,
`python -m cefc_mj.eval.paired`, and the test ledger's reader, writer and pre-flight check; then a few
real CLI processes. A checkpoint is checked whole (every zip member's CRC-32, its headers against the
zip directory, the end records), so a flipped bit of one is refused wherever it lands but in the two
version fields of the zip64 end record (4 bytes of a file, which no reader uses). A text file (MJCF,
JSON, the ledger) has no checksum: a flipped bit that leaves a valid file of its kind (a digit of a mass, a letter of a
command) is loaded and checked like any other file of that kind; those are counted apart.

    pytest -q -s tests/test_bad_files.py     # prints the counts per loader and kind of bad file
"""

from __future__ import annotations

import collections
import io
import json
import os
import pathlib
import random
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import torch

from cefc_mj import paths
from cefc_mj.errors import CefcError

SEED = 20261206
POLICIES = paths.POLICIES_DIR
ATM = POLICIES / "atm_c6_step3.pt"
ADVERSARY = POLICIES / "adversary_ppo.pt"
HIGH_LEVEL = POLICIES / "benchmarl_mappo.pt"
IRIS = paths.MJCF_DIR / "iris.xml"
TABLE8 = paths.EVAL_DIR / "reports" / "mujoco_ft" / "default_nav" / "table8.json"
LEDGER = paths.EVAL_DIR / "test_ledger.jsonl"
BIN = Path(sys.executable).parent
LOW = ["lowlevel", "--formation", "3", "--step", "1"]
TINY = ["--budget", "1", "--envs", "2", "--threads", "1", "--no-progress"]

COUNTS: collections.Counter = collections.Counter()
"""(loader, kind, outcome) -> files: printed at the end (-s), the numbers the docs quote."""


class Evil:
    """A pickled object of a class outside the weights-only allowlist."""


def _listing(folder: Path) -> dict[str, tuple[int, int] | None]:
    """Every path under `folder`, a file with its size and mtime: what 'nothing written' compares (a
    folder's own mtime is left out: the writability probe of an output folder leaves nothing in it)."""
    return {
        str(p.relative_to(folder)): None if p.is_dir() else (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
    }


def _refused(call, path: Path, loader: str, kind: str) -> str:
    """`call()` must raise CefcError with one non-empty line naming `path`'s file; returns the line."""
    with pytest.raises(CefcError) as refused:
        call()
    message = str(refused.value)
    assert message and "\n" not in message and path.name in message, (loader, kind, message)
    COUNTS[(loader, kind, "refused")] += 1
    return message


def _mutations(data: bytes, rng: random.Random, truncations: int, flips: int, cut_below: int | None = None):
    """(kind, bytes): `truncations` prefixes cut at random offsets below `cut_below` (default the
    length), `flips` copies with one random bit flipped."""
    for offset in sorted(rng.sample(range(cut_below or len(data)), truncations)):
        yield "truncated", data[:offset]
    for position in rng.sample(range(len(data)), flips):
        flipped = bytearray(data)
        flipped[position] ^= 1 << rng.randrange(8)
        yield "bit flip", bytes(flipped)


def _zip_without(source: Path, member_suffix: str) -> bytes:
    """`source`'s zip archive rewritten without the members whose name ends in `member_suffix`."""
    out = io.BytesIO()
    with zipfile.ZipFile(source) as src, zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            if not info.filename.endswith(member_suffix):
                dst.writestr(info.filename, src.read(info))
    return out.getvalue()


def _common_bad_files(folder: Path, rng: random.Random, source: Path, suffix: str) -> list[tuple[str, Path]]:
    """The files that are wrong whatever the loader: empty, text, random bytes, zips without the
    expected member, pickles with refused globals, a folder. Torch-specific ones come from `source`."""
    folder.mkdir(parents=True, exist_ok=True)
    payload = torch.load(source, weights_only=True)
    files = {
        "empty file": b"",
        "text file": b"root:x:0:0:root:/root:/bin/bash\ndaemon:x:1:1::/usr/sbin:/usr/sbin/nologin\n",
        "text file (JSON)": json.dumps({"format": payload["format"], "version": 1}).encode(),
        "random bytes": rng.randbytes(4096),
        "zip without the expected member": _zip_without(source, "data.pkl"),
        "zip without the expected member (a tensor)": _zip_without(source, "data/0"),
    }
    other_zip = io.BytesIO()
    with zipfile.ZipFile(other_zip, "w") as archive:
        archive.writestr("archive/notes.txt", "no checkpoint here")
    files["zip of something else"] = other_zip.getvalue()
    out = []
    for i, (kind, data) in enumerate(files.items()):
        path = folder / f"common{i}{suffix}"
        path.write_bytes(data)
        out.append((kind, path))
    for i, extra in enumerate((Evil(), pathlib.PurePosixPath("/etc"))):
        path = folder / f"global{i}{suffix}"
        torch.save({**payload, "meta": {"obj": extra}}, path)
        out.append(("pickle with a disallowed global", path))
    path = folder / f"legacy{suffix}"
    torch.save(payload, path, _use_new_zipfile_serialization=False)
    out.append(("not a zip archive (torch's pre-1.6 format)", path))
    (folder / f"folder{suffix}").mkdir()
    out.append(("a folder", folder / f"folder{suffix}"))
    return out


def _bad_checkpoints(folder: Path, rng: random.Random, source: Path, truncations: int, flips: int):
    """(kind, path) of every bad file made from the checkpoint `source`."""
    folder.mkdir(parents=True, exist_ok=True)
    out = _common_bad_files(folder / "common", rng, source, ".pt")
    for i, (kind, data) in enumerate(_mutations(source.read_bytes(), rng, truncations, flips)):
        path = folder / f"m{i}.pt"
        path.write_bytes(data)
        out.append((kind, path))
    return out


def _other_network(folder: Path, source: Path, **changes) -> Path:
    """`source` with its network description changed (the weights and their digest kept)."""
    payload = torch.load(source, weights_only=True)
    for key, value in changes.items():
        payload["net"][key] = value
    path = folder / f"other_network_{'_'.join(changes)}.pt"
    torch.save(payload, path)
    return path


@pytest.fixture(scope="module")
def trained_state(tmp_path_factory) -> Path:
    """A real training state (c = 3, Step 1, one iteration of 2 envs), written by train_lowlevel."""
    from cefc_mj.train.config import Budget, LowLevelConfig, PPOConfig
    from cefc_mj.train.lowlevel import train_lowlevel

    out = tmp_path_factory.mktemp("state")
    torch.set_num_threads(1)
    cfg = LowLevelConfig(formation=3, step=1, budget=Budget(iterations=1), ppo=PPOConfig(n_envs=2, update_threads=1))
    train_lowlevel(cfg, out / "runs", out / "policies", show_progress=False, evaluate=False)
    return out / "runs" / "atm_c3_step1" / "state.pt"


@pytest.fixture(scope="module", autouse=True)
def print_counts():
    yield
    loaders = sorted({loader for loader, _, _ in COUNTS})
    print(f"\nbad files: {sum(COUNTS.values())}")
    for loader in loaders:
        rows = {(k, o): n for (lo, k, o), n in COUNTS.items() if lo == loader}
        print(f"  {loader}: {sum(rows.values())}")
        for (kind, outcome), n in sorted(rows.items()):
            print(f"    {kind:48s} {outcome:28s} {n}")


# ---------------------------------------------------------------------------- checkpoints
def test_policy_files_of_every_level(tmp_path):
    """load_policy (AT-M), the adversary loader (as --adversary resolves it) and the high-level loader
    (BenchMARL exports included): every bad file refused in one line, nothing written."""
    from cefc_mj.eval.highlevel import resolve_adversary
    from cefc_mj.nn.highlevel_policy import load_highlevel_policy
    from cefc_mj.nn.policy_io import load_policy

    rng = random.Random(SEED)
    obs_dim = load_policy(ATM).obs_dim
    cases = {
        "load_policy": (
            lambda p: load_policy(p, obs_dim=obs_dim),
            _bad_checkpoints(tmp_path / "atm", rng, ATM, 40, 40)
            + [
                ("checkpoint of another network", ADVERSARY),
                ("checkpoint of another network", HIGH_LEVEL),
                ("checkpoint of another network", _other_network(tmp_path / "atm", ATM, hidden=64)),
                ("checkpoint of another network", _other_network(tmp_path / "atm", ATM, max_neighbours=9)),
            ],
        ),
        "adversary (--adversary)": (
            lambda p: resolve_adversary(str(p)),
            _bad_checkpoints(tmp_path / "adv", rng, ADVERSARY, 25, 25)
            + [
                ("checkpoint of another network", ATM),
                ("checkpoint of another network", HIGH_LEVEL),
                ("checkpoint of another network", _other_network(tmp_path / "adv", ADVERSARY, hidden=32)),
            ],
        ),
        "high-level policy (BenchMARL export)": (
            load_highlevel_policy,
            _bad_checkpoints(tmp_path / "hl", rng, HIGH_LEVEL, 10, 10)
            + [("checkpoint of another network", ATM), ("checkpoint of another network", ADVERSARY)],
        ),
    }
    before = _listing(tmp_path)
    for loader, (load, files) in cases.items():
        for kind, path in files:
            _refused(lambda: load(path), path, loader, kind)
    assert _listing(tmp_path) == before


def _train_refusal(argv, capsys) -> str:
    """cefc-train in-process: exit 2, exactly one line on stderr."""
    from cefc_mj.cli.train import main

    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    return err.strip()


def test_init_from_and_resume(tmp_path, trained_state, capsys):
    """--init-from and --resume through the in-process CLI: exit 2, one line naming the file, and the
    run folders exactly as they were (nothing written, no run started)."""
    rng = random.Random(SEED + 1)
    out = tmp_path / "out"
    out.mkdir()
    init_files = _bad_checkpoints(tmp_path / "init", rng, ATM, 15, 15) + [
        ("checkpoint of another network", ADVERSARY),
        ("checkpoint of another network", POLICIES / "atm_student.pt"),
        ("checkpoint of another network", _other_network(tmp_path / "init", ATM, max_neighbours=9)),
    ]
    before = _listing(tmp_path)
    step3 = ["lowlevel", "--formation", "6", "--step", "3", "--budget", "1", "--out", str(out)]
    for kind, path in init_files:
        message = _train_refusal([*step3, "--init-from", str(path)], capsys)
        assert path.name in message and "--init-from" in message, message
        COUNTS[("--init-from", kind, "refused")] += 1
    assert _listing(tmp_path) == before

    resume_files = _bad_checkpoints(tmp_path / "resume", rng, trained_state, 15, 15) + [
        ("checkpoint of another network (a policy file)", ATM),
    ]
    run = tmp_path / "runs" / "atm_c3_step1"
    run.mkdir(parents=True)
    argv = [*LOW, *TINY, "--resume", "--out", str(tmp_path / "runs"), "--policies-dir", str(tmp_path / "policies")]
    for kind, path in resume_files:
        target = run / "state.pt"
        if target.is_dir():
            target.rmdir()
        if path.is_dir():
            target.unlink(missing_ok=True)
            target.mkdir()
        else:
            shutil.copyfile(path, target)
        before = _listing(tmp_path)
        message = _train_refusal(argv, capsys)
        assert "state.pt" in message, message
        assert _listing(tmp_path) == before
        COUNTS[("--resume", kind, "refused")] += 1
    # the state of a run of another formation, in the run folder of this one
    other = tmp_path / "runs" / "atm_c4_step1"
    other.mkdir()
    shutil.copyfile(trained_state, other / "state.pt")
    before = _listing(tmp_path)
    argv = ["lowlevel", "--formation", "4", "--step", "1", *argv[len(LOW) :]]
    assert "made with different settings (formation" in _train_refusal(argv, capsys)
    assert _listing(tmp_path) == before
    COUNTS[("--resume", "checkpoint of another formation", "refused")] += 1


# ---------------------------------------------------------------------------- other files users give
def _text_bad_files(folder: Path, rng: random.Random, suffix: str) -> list[tuple[str, Path]]:
    """Empty, text of another kind, random bytes, a zip and a folder."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {
        "empty file": b"",
        "text file": b"root:x:0:0:root:/root:/bin/bash\n",
        "random bytes": rng.randbytes(4096),
        "zip of something else": ATM.read_bytes(),
    }
    out = []
    for i, (kind, data) in enumerate(files.items()):
        (folder / f"c{i}{suffix}").write_bytes(data)
        out.append((kind, folder / f"c{i}{suffix}"))
    (folder / f"folder{suffix}").mkdir()
    return out + [("a folder", folder / f"folder{suffix}")]


def _error_or_valid(load, path: Path, loader: str, kind: str) -> None:
    """A text file with a flipped bit: refused in one line, or a valid file of its kind (loaded)."""
    try:
        load(path)
    except CefcError as e:
        assert str(e) and "\n" not in str(e) and path.name in str(e), (loader, kind, str(e))
        COUNTS[(loader, kind, "refused")] += 1
    else:
        COUNTS[(loader, kind, "still a valid file: loaded")] += 1


def test_airframe_mjcf(tmp_path, capsys):
    """--airframe: every bad MJCF file is refused in one line (in-process cefc-eval: exit 2, no report)."""
    from cefc_mj.cli.eval import main
    from cefc_mj.control.airframe import load_airframe

    rng = random.Random(SEED + 2)
    data = IRIS.read_bytes()
    files = _text_bad_files(tmp_path / "af", rng, ".xml") + [
        ("another MJCF (a world, not an airframe)", paths.MJCF_DIR / "arena.xml")
    ]
    flips = []
    for i, (kind, mutated) in enumerate(_mutations(data, rng, 25, 25, cut_below=data.rindex(b"</mujoco>"))):
        (tmp_path / f"m{i}.xml").write_bytes(mutated)
        (flips if kind == "bit flip" else files).append((kind, tmp_path / f"m{i}.xml"))
    before = _listing(tmp_path)
    for kind, path in files:
        _refused(lambda: load_airframe(path), path, "--airframe", kind)
    for kind, path in flips:
        _error_or_valid(load_airframe, path, "--airframe", kind)
    for kind, path in files[:6]:  # the CLI: exit 2, one line, before any episode
        with pytest.raises(SystemExit) as exit_info:
            main(
                ["--backend", "mujoco", "--airframe", str(path), "--episodes", "1", "--json", str(tmp_path / "r.json")]
            )
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and err.count("\n") == 1 and path.name in err, err
    assert _listing(tmp_path) == before


def test_paired_reports(tmp_path, capsys):
    """python -m cefc_mj.eval.paired: a bad report is refused in one line naming it (exit 2, no --md)."""
    from cefc_mj.eval.paired import main, read_report

    rng = random.Random(SEED + 3)
    data = TABLE8.read_bytes()
    report = json.loads(data)
    folder = tmp_path / "reports"
    files = _text_bad_files(folder, rng, ".json")
    for kind, content in (
        ("JSON of another kind (a list)", [report]),
        (
            "JSON of another kind (a table5 report)",
            json.loads((paths.EVAL_DIR / "reports/prereg/table5.json").read_text()),
        ),
        (
            "a report without its calm cells",
            {
                **report,
                "rows": {c: {k: v for k, v in row.items() if k != "SITL-S"} for c, row in report["rows"].items()},
            },
        ),
    ):
        path = folder / f"kind{len(files)}.json"
        path.write_text(json.dumps(content) if not isinstance(content, str) else content)
        files.append((kind, path))
    nan = json.loads(data)
    first_cell = next(iter(next(iter(nan["rows"].values())).values()))
    first_cell["episodes_detail"][0]["F"] = float("nan")
    (folder / "nan.json").write_text(json.dumps(nan))
    files.append(("a report with a figure that is not a number", folder / "nan.json"))
    flips = []
    for i, (kind, mutated) in enumerate(_mutations(data, rng, 25, 25, cut_below=len(data.rstrip()))):
        (folder / f"m{i}.json").write_bytes(mutated)
        (flips if kind == "bit flip" else files).append((kind, folder / f"m{i}.json"))
    md = tmp_path / "out.md"
    before = _listing(tmp_path)
    for kind, path in files:
        _refused(lambda: read_report(path), path, "paired (JSON report)", kind)
    for kind, path in flips:
        _error_or_valid(read_report, path, "paired (JSON report)", kind)
    for kind, path in files:  # the command: exit 2, one line naming the file, nothing written
        assert main([str(path), str(TABLE8), "--md", str(md)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and path.name in err, err
    assert _listing(tmp_path) == before


def test_the_test_ledger(tmp_path, monkeypatch, capsys):
    """The ledger's reader, writer and pre-flight check refuse a damaged ledger the same way (one line
    naming the file and line), and cefc-eval refuses to fly a test batch over it: nothing appended."""
    from cefc_mj.cli.eval import main
    from cefc_mj.eval import ledger

    rng = random.Random(SEED + 4)
    data = LEDGER.read_bytes()
    folder = tmp_path / "ledgers"
    files = [(k, p) for k, p in _text_bad_files(folder, rng, ".jsonl") if k != "empty file"]  # empty: no flights
    (folder / "empty.jsonl").write_bytes(b"")
    assert ledger.read_ledger(folder / "empty.jsonl").flights == []
    line_ends = {i + 1 for i, b in enumerate(data) if b == ord("\n")}
    flips = []
    mid_line = [k for k in range(1, len(data)) if k not in line_ends]  # a cut at a line's end is a shorter ledger
    for i, offset in enumerate(sorted(rng.sample(mid_line, 25))):
        (folder / f"t{i}.jsonl").write_bytes(data[:offset])
        files.append(("truncated", folder / f"t{i}.jsonl"))
    for i, (_, mutated) in enumerate(_mutations(data, rng, 0, 25)):
        (folder / f"f{i}.jsonl").write_bytes(mutated)
        flips.append(("bit flip", folder / f"f{i}.jsonl"))
    before = _listing(tmp_path)

    def every_reader_and_writer(kind: str, path: Path) -> None:
        message = _refused(lambda: ledger.read_ledger(path), path, "test ledger (reader)", kind)
        monkeypatch.setenv(ledger.ENV_VAR, str(path))
        check = _refused(
            lambda: ledger.check_before_flight("single", 10000, 1), path, "test ledger (pre-flight check)", kind
        )
        write = _refused(lambda: ledger.record_flight("table8", 10000, 20, "cmd"), path, "test ledger (writer)", kind)
        assert check == write == message

    for kind, path in files:
        every_reader_and_writer(kind, path)
    for kind, path in flips:
        try:
            ledger.read_ledger(path)
        except CefcError:
            every_reader_and_writer(kind, path)
        else:
            COUNTS[("test ledger (reader)", kind, "still a valid file: read")] += 1
    for kind, path in files[:4]:  # cefc-eval refuses before flying a test batch over it
        monkeypatch.setenv(ledger.ENV_VAR, str(path))
        with pytest.raises(SystemExit) as exit_info:
            main(["--formation", "5", "--seed", "10000", "--episodes", "1"])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and err.count("\n") == 1 and path.name in err, err
    assert _listing(tmp_path) == before


# ---------------------------------------------------------------------------- real processes
def test_real_cli_processes(tmp_path):
    """A few real command lines, run at once: exit 2, one line on stderr, no traceback, nothing written
    (--resume and the others run through the same `main` in-process above)."""
    rng = random.Random(SEED + 5)
    atm = ATM.read_bytes()
    cut = tmp_path / "cut.pt"
    cut.write_bytes(atm[: rng.randrange(len(atm))])
    flipped = bytearray(atm)
    flipped[rng.randrange(len(atm))] ^= 1 << rng.randrange(8)
    (tmp_path / "flip.pt").write_bytes(bytes(flipped))
    broken_ledger = tmp_path / "ledger.jsonl"
    broken_ledger.write_bytes(LEDGER.read_bytes() + b'{"kind": "fli')
    out = tmp_path / "out"
    commands = {
        "cefc-eval --policy (truncated)": ([BIN / "cefc-eval", "--policy", cut, "--json", out / "r.json"], {}),
        "cefc-train --init-from (bit flip)": (
            [BIN / "cefc-train", "lowlevel", "--formation", "6", "--step", "3", "--init-from", tmp_path / "flip.pt"]
            + ["--budget", "1it", "--out", out],
            {},
        ),
        "cefc-eval over a damaged test ledger": (
            [BIN / "cefc-eval", "--formation", "5", "--seed", "10000", "--episodes", "1"],
            {"CEFC_TEST_LEDGER": str(broken_ledger)},
        ),
    }
    before = _listing(tmp_path)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    started = {
        name: subprocess.Popen(
            [str(a) for a in argv],
            cwd=tmp_path,
            env={**env, **extra},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for name, (argv, extra) in commands.items()
    }
    for name, process in started.items():
        _, err = process.communicate(timeout=120)
        assert process.returncode == 2 and err.count("\n") == 1 and "Traceback" not in err, (name, err)
        COUNTS[("real CLI processes", name, "refused")] += 1
    assert _listing(tmp_path) == before
