"""examples/px4_exact_table8.py: the four grids' commands on the declared test batch, the one table and
its targets read from hand-made table8.json files (a met and a missed target each), and a flown grid
refused a second flight."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from cefc_mj.seeds import TABLE8_PX4_TEST_SEEDS, TEST_BATCHES

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "px4_exact_table8.py"


def load_script():
    spec = importlib.util.spec_from_file_location("px4_exact_table8", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_list_names_the_paper_agents_flight_of_each_grid_on_the_declared_batch(capsys):
    module = load_script()
    assert module.main(["--list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4 and all(line.startswith(("todo", "flown")) for line in lines)
    for line in lines:
        for flag in ("--offboard acceleration", "--estimator raw", "--guard off", "--seed 70000", "--episodes 20"):
            assert flag in line
    assert TABLE8_PX4_TEST_SEEDS == list(range(70000, 70020))
    batch = next(b for b in TEST_BATCHES if b.first == 70000)
    assert batch.family == "formation" and batch.count == 20


def write_grid(folder: Path, retention: dict[str, float], calm_c: float, dev08_c: float, calm_fn=(900.0, 800.0)):
    rows = {}
    for c in ("5", "6", "7", "8"):
        f, n = calm_fn
        cells = {"SITL-S": {"F": f, "N": n, "C": calm_c, "FN": f + n, "episodes": 20}}
        for cond in ("Wind-3", "Wind-5", "Wind-8", "Deviation-0.3", "Deviation-0.5", "Deviation-0.8"):
            kept = retention.get(cond, 1.0)
            cells[cond] = {"F": f * kept, "N": n * kept, "C": dev08_c if cond == "Deviation-0.8" else 0.0}
            cells[cond].update(FN=(f + n) * kept, episodes=20)
        rows[c] = cells
    folder.mkdir(parents=True)
    (folder / "table8.json").write_text(json.dumps({"rows": rows}))


def test_report_reads_every_target_met_or_missed(tmp_path, monkeypatch):
    module = load_script()
    monkeypatch.setattr(module, "ROOT", tmp_path)
    out = tmp_path / module.TEST_OUT
    write_grid(out / "push", {"Wind-3": 0.95, "Wind-5": 0.60}, calm_c=0.0, dev08_c=0.5)
    write_grid(out / "bound3.5", {"Wind-8": 0.90}, calm_c=0.02, dev08_c=5.0, calm_fn=(500.0, 800.0))
    text, numbers = module.report(validation=False)
    assert numbers["cells"]["6"]["Wind-5"]["push"]["retention"] == pytest.approx(0.60)
    found = module.targets(numbers)
    assert "push Wind-5 keeps >= 85%: lowest over c 60.0% (missed by 25.0%)" in found
    assert "push Wind-3 keeps >= 90%: lowest over c 95.0% (met)" in found
    assert "bound3.5 Wind-8 keeps >= 85%: lowest over c 90.0% (met)" in found
    assert "push calm C 0: highest over c 0.000 % (met)" in found
    assert "bound3.5 calm C 0: highest over c 0.020 % (missed)" in found
    assert any(t.startswith("bound3.5 calm F at or above the paper's SITL-S: c = 5: 500 <") for t in found)
    assert any(t.startswith("bound3.5 Deviation-0.8 C below the paper's: c = 5: 5.000 >=") for t in found)
    assert "| 6 | Wind-5 | 60.0%, C 0.000 | 100.0%, C 0.000 |" in text


def test_a_grid_the_ledger_holds_is_not_flown_again(monkeypatch, capsys):
    module = load_script()
    monkeypatch.setattr(module, "flown_in_ledger", lambda slug: slug == "nav")
    monkeypatch.setattr(module, "fly", lambda *a: pytest.fail("flew"))
    with pytest.raises(SystemExit) as exit_info:
        module.main(["--fly", "--grid", "nav"])
    assert exit_info.value.code == 2
    assert "the test batch was flown for nav" in capsys.readouterr().err
