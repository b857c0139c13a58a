"""The measured trade table that substeps = "auto" reads (analysis/trade_table.py): the package ships exactly what
its studies give, with their provenance; a scene matches the problem it was measured on whatever its precision,
and nothing else; a missing or malformed table says so."""

import json
import math
import pathlib

import pytest

from warpspring.analysis import trade_contact
from warpspring.analysis.trade_table import (FLOOR_INTEGRATORS, TABLE_PATH, load_table, signature, signatures_match,
                                             table_from_studies)
from warpspring.errors import ConfigError

ROOT = pathlib.Path(__file__).parents[1]


def test_the_shipped_table_is_what_its_studies_give(monkeypatch):
    """Rebuilt from the studies it names (their CSV and reports under bench/results/), the table is the file the
    package ships: no hand-edited number, and a stale table (a scene changed since) fails here."""
    shipped = json.loads(TABLE_PATH.read_text())
    monkeypatch.chdir(ROOT)  # the sources are named relative to the repository
    rebuilt = json.loads(json.dumps(table_from_studies([s["file"] for s in shipped["sources"]])))
    assert rebuilt == shipped
    for source in shipped["sources"]:
        assert source["command"].startswith("warpspring trade") and source["warp"] and source["date"]
        assert source["device"] in source["command"] and source["device_name"]
    assert TABLE_PATH.stat().st_size < 40_000  # small package data (34 kB)


def test_the_floor_is_the_geometric_mean_of_its_rows():
    table = load_table()
    assert [r.integrator for r in table.floor_rows] == list(FLOOR_INTEGRATORS)
    assert all(r.problem == "cloth" and r.precision == "float64" for r in table.floor_rows)
    assert table.floor == pytest.approx(math.sqrt(table.floor_rows[0].error * table.floor_rows[1].error), rel=1e-12)
    assert 1e-4 < table.floor < 1e-2  # between the explicit integrators' errors at their largest steps, in metres
    assert "geometric mean of symplectic_euler" in table.floor_reason()


def test_a_scene_matches_its_measured_problem_only():
    """float32 and float64 builds of a measured scene match its entry; another contact option matches its own; a
    changed parameter matches none."""
    table = load_table()
    drape, stack = trade_contact.FULL_PROBLEMS["drape"], trade_contact.FULL_PROBLEMS["stack"]
    for precision in ("float32", "float64"):
        model = drape.build("cpu", precision, drape.scene.option("particle contacts"))
        assert table.match(model) == ("drape", "particle contacts")
    assert table.match(stack.build("cpu", "float32", stack.scene.option("τ = 10 mm"))) == ("stack", "τ = 10 mm")
    smaller = trade_contact.QUICK_PROBLEMS["drape"]  # 8² instead of 16²: not measured in the shipped table
    assert table.match(smaller.build("cpu", "float32", drape.scene.option("particle contacts"))) is None
    # Every measured option's rows are clean runs: errors in metres, substeps at the study's 60 frames/s.
    for (problem, option), (sig, rows) in table.problems.items():
        assert rows and all(r.error > 0 and r.substeps(60.0) >= 5 for r in rows), (problem, option)
        assert signatures_match(sig, sig)


def test_signatures_compare_floats_within_a_tolerance():
    a = {"n": 3, "x": [1.0, 2.0], "on": True, "tau": None}
    assert signatures_match(a, {"n": 3, "x": [1.0 + 1e-7, 2.0], "on": True, "tau": None})
    assert not signatures_match(a, {"n": 3, "x": [1.001, 2.0], "on": True, "tau": None})
    assert not signatures_match(a, {"n": 4, "x": [1.0, 2.0], "on": True, "tau": None})
    assert not signatures_match(a, {"n": 3, "x": [1.0, 2.0], "on": True, "tau": 0.004})
    assert not signatures_match(a, {"n": 3, "x": [1.0], "on": True, "tau": None})


def test_a_missing_or_malformed_table_says_so(tmp_path):
    with pytest.raises(ConfigError, match="trade table not found"):
        load_table(tmp_path / "none.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": 1, "floor": {}}))
    with pytest.raises(ConfigError, match="is not a warpspring trade table"):
        load_table(bad)


def test_signature_is_json_ready():
    """A voxel ball is springs; the neo-Hookean one's tets are a family: both counted, the mesh's inside test named."""
    for name, families in (("softball", False), ("softball-neohookean", True)):
        spec = trade_contact.FULL_PROBLEMS[name]
        sig = signature(spec.build("cpu", "float32", spec.scene.option("pseudo-normals")))
        assert json.loads(json.dumps(sig)) == sig
        assert sig["shapes"][0]["kind"] == "mesh" and sig["shapes"][0]["winding_number"] is False
        assert bool(sig["families"]) is families and (sig["springs"] > 0) is not families
