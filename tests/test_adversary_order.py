"""examples/adversary_order.py: the report builder's means, CIs and Welch differences on a small
hand-made flights document (checked against scipy directly), the order it names, the Markdown and the
figure; bad input (a test-block seed, a flights file of another protocol) exits 2 with one line and
flies nothing."""

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "adversary_order.py"


def load_script():
    spec = importlib.util.spec_from_file_location("adversary_order", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# Per training seed, E and R_H episode means (per-episode sums, steps) of each method against each adversary.
E = {
    ("CI-HRL", "r_largest"): [100.0, 120.0, 110.0],
    ("MAPPO+AT-M", "r_largest"): [60.0, 80.0, 75.0],  # MAPPO lower: ahead on E
    ("CI-HRL", "nearest_group"): [40.0, 50.0, 45.0],
    ("MAPPO+AT-M", "nearest_group"): [90.0, 95.0, 99.0],  # the order flipped
}


def synthetic_doc(module) -> dict:
    flights = {}
    for (method, adversary), values in E.items():
        stem = dict(module.METHODS)[method]
        for seed, e in zip((100, 101, 102), values):
            file = f"{stem}_seed{seed}.pt"
            flights[module.flight_key(file, adversary)] = {
                "policy": file,
                "method": method,
                "training_seed": seed,
                "adversary": adversary,
                "E": e,
                "R_H": -10.0 * e,
            }
    return {"protocol": module.protocol(3, 200), "flights": flights}


def test_report_means_cis_and_welch_difference_match_scipy():
    module = load_script()
    report = module.build_report(synthetic_doc(module))
    assert [a["adversary"] for a in report["adversaries"]] == ["r_largest", "nearest_group"]  # ADVERSARIES order
    assert "EXPLORATORY" in report["label"]
    for entry in report["adversaries"]:
        cihrl = np.array(E["CI-HRL", entry["adversary"]]) * 0.1
        mappo = np.array(E["MAPPO+AT-M", entry["adversary"]]) * 0.1
        block = entry["methods"]["CI-HRL"]["E"]
        assert math.isclose(block["mean"], cihrl.mean())
        low, high = stats.t.interval(0.95, df=2, loc=cihrl.mean(), scale=cihrl.std(ddof=1) / math.sqrt(3))
        assert math.isclose(block["ci_low"], low) and math.isclose(block["ci_high"], high)
        d = entry["difference"]["E"]
        assert math.isclose(d["difference"], mappo.mean() - cihrl.mean())
        assert math.isclose(d["p"], stats.ttest_ind(mappo, cihrl, equal_var=False).pvalue)
        ci = stats.ttest_ind(mappo, cihrl, equal_var=False).confidence_interval(0.95)
        assert math.isclose(d["ci_low"], ci.low) and math.isclose(d["ci_high"], ci.high)
        assert math.isclose(entry["difference"]["R_H"]["difference"], -10.0 * d["difference"])
    ps = [a["difference"][m]["p"] for a in report["adversaries"] for m in ("E", "R_H")]
    holm = [a["difference"][m]["p_holm"] for a in report["adversaries"] for m in ("E", "R_H")]
    assert math.isclose(min(holm), min(1.0, 4 * min(ps))) and all(h >= p for h, p in zip(holm, ps))
    by = {a["adversary"]: a for a in report["adversaries"]}
    # Neither adversary is the game's: no seed flown against both, so no ratio.
    assert by["r_largest"]["E_vs_game_adversary"]["CI-HRL"] == {"seeds": 0, "ratio": None, "p_weaker": None}
    assert by["r_largest"]["lower_E"] == "MAPPO+AT-M" and by["r_largest"]["higher_R_H"] == "MAPPO+AT-M"
    assert by["nearest_group"]["lower_E"] == "CI-HRL" and by["nearest_group"]["higher_R_H"] == "CI-HRL"


def test_report_markdown_and_figure(tmp_path):
    module = load_script()
    doc = synthetic_doc(module)
    game = module.ADVERSARIES[0][1]
    for key, flight in list(doc["flights"].items()):  # the game's adversary twice as dangerous as R-Largest
        if flight["adversary"] == "r_largest":
            doc["flights"][key.replace("r_largest", game)] = {**flight, "adversary": game, "E": 2 * flight["E"]}
    report = module.write_report(doc, tmp_path)
    assert report["adversaries"][1]["E_vs_game_adversary"]["MAPPO+AT-M"]["ratio"] == 0.5
    text = (tmp_path / "report.md").read_text()
    assert "EXPLORATORY" in text and "| R-Largest | 3/3 | 11.00 [" in text and "| Nearest-group rule | 3/3 |" in text
    assert "| R-Largest | 0.50, p 0.0014 | 0.50, p 0.0035 |" in text  # one-sided paired t over 3 seeds
    assert json.loads((tmp_path / "report.json").read_text()) == json.loads(json.dumps(report))
    assert (tmp_path / "adversary_order.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_test_block_seed_exits_2_before_flying(tmp_path, capsys):
    module = load_script()
    assert module.main(["--seed", "10000", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("adversary_order.py: error: --seed 10000: in the test block") and "\n" not in err
    assert not any(tmp_path.iterdir())


def test_flights_of_another_protocol_are_not_resumed(tmp_path, capsys):
    module = load_script()
    (tmp_path / "flights.json").write_text(json.dumps({"protocol": module.protocol(7, 200), "flights": {}}))
    assert module.main(["--list", "--out", str(tmp_path)]) == 2
    assert "flown with another protocol (7 games of batch seed 200" in capsys.readouterr().err
    assert module.main(["--list", "--episodes", "7", "--out", str(tmp_path)]) == 0


@pytest.mark.slow
def test_smoke_flies_real_files_and_resumes(tmp_path, capsys):
    """--smoke: 8 real flights of the shipped pre-registered files; a rerun flies none and rebuilds the report."""
    module = load_script()
    assert module.main(["--smoke", "--workers", "1", "--out", str(tmp_path)]) == 0
    flights = json.loads((tmp_path / "flights.json").read_text())["flights"]
    assert len(flights) == 8 and {f["adversary"] for f in flights.values()} == {"adversary_ddpg", "r_largest"}
    assert all(
        len(f["per_episode"]["E"]) == 4 and math.isclose(f["E"], np.mean(f["per_episode"]["E"]))
        for f in flights.values()
    )
    capsys.readouterr()
    assert module.main(["--smoke", "--out", str(tmp_path)]) == 0
    assert "8 of 8 flights done; flying 0" in capsys.readouterr().out
    assert json.loads((tmp_path / "flights.json").read_text())["flights"] == flights
