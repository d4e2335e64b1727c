"""Shipped reports and model cards name files by paths relative to the checkout (or the run's working
folder), never by the absolute paths of the machine that made them; the writers use display_path."""

from __future__ import annotations

import json
import re
from pathlib import Path

from cefc_mj import paths
from cefc_mj.eval.runner import policy_files
from cefc_mj.provenance import display_path

ABSOLUTE = re.compile(r"(?:^|[\s`(\"'=])(/(?:[\w.-]+/)+[\w.-]*)")


def _shipped_files() -> list[Path]:
    found = [p for p in (paths.EVAL_DIR / "reports").rglob("*") if p.suffix in (".json", ".jsonl", ".md", ".csv")]
    return found + sorted(paths.POLICIES_DIR.glob("*.json"))


def _strings(value):
    if isinstance(value, dict):
        for v in value.values():
            yield from _strings(v)
    elif isinstance(value, list):
        for v in value:
            yield from _strings(v)
    elif isinstance(value, str):
        yield value


def test_no_shipped_report_or_card_holds_an_absolute_path():
    files = _shipped_files()
    assert len(files) > 50
    offenders = []
    for path in files:
        text = path.read_text()
        if path.suffix == ".json":
            texts = list(_strings(json.loads(text)))
        elif path.suffix == ".jsonl":
            texts = [s for line in text.splitlines() if line.strip() for s in _strings(json.loads(line))]
        else:
            texts = [text]
        offenders += [f"{path.name}: {m}" for t in texts for m in ABSOLUTE.findall(t)]
    assert not offenders, offenders[:10]


def test_writers_record_paths_relative_to_the_checkout(tmp_path, monkeypatch):
    assert policy_files("nav", [6])["6"]["file"] == "policies/atm_c6_nav.pt"
    assert display_path(paths.POLICIES_DIR) == "policies"
    monkeypatch.chdir(tmp_path)
    assert display_path(tmp_path / "runs" / "x") == "runs/x"
    assert display_path("/") == "/"  # outside both: nothing shorter is true
