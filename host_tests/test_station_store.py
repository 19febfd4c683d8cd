"""The results database (``motorjig.station.store``, ``jigctl results``) on SQLite and on PostgreSQL.

The same runs go into a SQLite file and into a real PostgreSQL server (a temporary
cluster started for this module, ``station.pgtemp``), and ``jigctl results`` must give
the same answers from both. Yield and Cpk are checked against numbers worked out by
hand below; two stations writing 200 runs each at the same moment lose nothing and
mix nothing; a database of an older schema version is upgraded (or refused when no
upgrade is known), a newer one is refused and left as it was; ``jigctl test`` stores
each run, and a run whose storing fails still has its files and says so. A multi-up
station's runs keep their slot, and yield and Cpk per slot are checked against numbers
worked out by hand too; a database of schema version 1 (before slots) is upgraded in place.
"""

import datetime
import itertools
import json
import os
import subprocess
import sys
import time

import pytest
from sqlalchemy import create_engine, text

from motorjig import cli
from motorjig.station import store as S
from motorjig.station.pgtemp import TempCluster, find_bin

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SMOKE = os.path.join(ROOT, "plans", "smoke.toml")

# The known runs: 5 DUTs of plan "eol", 9 runs, stored out of time order (newest first) so
# that the first and last run of a DUT must come from the start times, not from the ids.
#
#   DUT  runs (in time order)      first  last
#   A    PASS                      PASS   PASS
#   B    FAIL, PASS                FAIL   PASS
#   C    FAIL, FAIL                FAIL   FAIL
#   D    PASS, FAIL                PASS   FAIL
#   E    ERROR, PASS               ERROR  PASS
#   first-pass yield 2/5 = 0.4, final yield 3/5 = 0.6
#
# Measurements, in the same order (minute 0..8):
KNOWN = [  # dut, verdict, duration_ratio, following_error, torque
    ("A", "PASS", 1.00, 2, 9.0),
    ("B", "FAIL", 1.02, 4, 8.0),
    ("C", "FAIL", 0.98, 6, 7.5),
    ("D", "PASS", 1.04, 8, 8.5),
    ("E", "ERROR", 0.96, 10, 9.5),
    ("B", "PASS", 1.01, 3, 8.2),
    ("C", "FAIL", 0.99, 5, 7.8),
    ("D", "FAIL", 1.03, 7, 8.8),
    ("E", "PASS", 0.97, 9, 9.2),
]
# duration_ratio, limits 0.85 <= x <= 1.15: sum 9.00, mean 1.00; deviations 0, ±.01, ±.02, ±.03, ±.04:
#   squares 2 * (1 + 4 + 9 + 16) e-4 = 0.006; variance 0.006 / 8 = 0.00075; sigma = 0.027386127875258306
#   Cpk = min(1.15 - 1, 1 - 0.85) / (3 sigma) = 0.15 / 0.082158383625774 = 1.8257418583505536
# following_error, limit x <= 20: sum 54, mean 6; deviations 0, ±1, ±2, ±3, ±4: squares 60; variance 7.5
#   sigma 2.7386127875258306; Cpk = (20 - 6) / (3 sigma) = 14 / 8.215838362577491 = 1.704025734460517
# torque, limit 5 <= x: sum 76.5, mean 8.5; deviations .5 -.5 -1 0 1 -.3 -.7 .3 .7: squares 3.66;
#   variance 0.4575, sigma 0.6763874629234342; Cpk = (8.5 - 5) / (3 sigma) = 1.7248496322273366
# alarm: always 0 (limit x == 0): sigma 0, Cpk None. samples: 30..38 without limits: Cpk None.
EXPECTED_STATS = {
    ("move", "duration_ratio"): dict(n=9, min=0.96, mean=1.0, max=1.04, sigma=0.027386127875258306,
                                     low=0.85, high=1.15, cpk=1.8257418583505536),
    ("move", "following_error"): dict(n=9, min=2.0, mean=6.0, max=10.0, sigma=2.7386127875258306,
                                      low=None, high=20.0, cpk=1.704025734460517),
    ("move", "alarm"): dict(n=9, min=0.0, mean=0.0, max=0.0, sigma=0.0, low=0.0, high=0.0, cpk=None),
    ("move", "samples"): dict(n=9, min=30.0, mean=34.0, max=38.0, sigma=2.7386127875258306, low=None,
                              high=None, cpk=None),
    ("home", "origin_ok"): dict(n=9, min=1.0, mean=1.0, max=1.0, sigma=0.0, low=1.0, high=1.0, cpk=None),
    ("home", "torque"): dict(n=9, min=7.5, mean=8.5, max=9.5, sigma=0.6763874629234342, low=5.0, high=None,
                             cpk=1.7248496322273366),
}
T0 = datetime.datetime(2026, 11, 2, 8, 0)  # local time; run k starts k hours later (days 2 and 3)
T0_MS = int(T0.astimezone().timestamp() * 1000)


def meas(name, value, validators=(), unit=None, outcome="PASS"):
    m = {"name": name, "outcome": outcome, "validators": list(validators)}
    if value is not None:
        m["measured_value"] = value
    if unit:
        m["units"] = {"name": unit, "code": unit, "suffix": unit}
    return m


def record(dut, verdict, start_ms, phases, plan="eol", version="1.0", station="st1"):
    t = start_ms
    out = []
    for name, ms in phases:
        out.append({"name": name, "outcome": "PASS" if all(m["outcome"] == "PASS" for m in ms) else "FAIL",
                    "start_time_millis": t, "end_time_millis": t + 100,
                    "measurements": {m["name"]: m for m in ms}, "attachments": {}})
        t += 100
    return {"dut_id": dut, "station_id": station, "start_time_millis": start_ms, "end_time_millis": t,
            "outcome": verdict, "outcome_details": [{"code": "X", "description": "lost"}] if verdict == "ERROR" else [],
            "metadata": {"test_name": plan, "test_version": version, "plan_hash": "ab" * 32,
                         "plan_file": "/plans/%s.toml" % plan, "operator": "anna",
                         "drive": {"slave": 2, "protocol": 6, "slave_type": 20, "name": "Ezi-STEP"}},
            "phases": out}


def known_record(k):
    dut, verdict, ratio, ferr, torque = KNOWN[k]
    return record(dut, verdict, T0_MS + k * 3600000, [
        ("preflight", []),
        ("identify", [meas("slave_name", "Ezi-STEP Plus-R", ["'x' matches /^Ezi/"]),
                      meas("motor", None, outcome="UNSET")]),
        ("move", [meas("duration_ratio", ratio, ["0.85 <= x <= 1.15"]),
                  meas("following_error", ferr, ["x <= 20"], "pulse"),
                  meas("alarm", 0, ["x == 0"]),
                  meas("samples", 30 + k)]),
        ("home", [meas("origin_ok", True, ["x == True"]),
                  meas("torque", torque, ["5 <= x"], "N·cm")]),
    ])


def store_known(db):
    with S.open_store(db) as st:
        ids = [st.add_run(known_record(k), {"json": "/r/run%d.json" % k}) for k in reversed(range(len(KNOWN)))]
    return ids


# --- the databases ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def pg():
    if find_bin() is None:
        pytest.skip("PostgreSQL server binaries (initdb, pg_ctl) not found: apt-get install postgresql "
                    "(tools/setup.sh does under CI)")
    with TempCluster() as cluster:
        yield cluster


_names = itertools.count()


def new_db(kind, request, tmp_path):
    if kind == "sqlite":
        return str(tmp_path / ("r%d.sqlite" % next(_names)))
    return request.getfixturevalue("pg").create_database("r%d" % next(_names))


@pytest.fixture(params=["sqlite", "postgresql"])
def db(request, tmp_path):
    return new_db(request.param, request, tmp_path)


def jigctl(capsys, *argv):
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


# --- storing and reading --------------------------------------------------------------------------

def test_limits_are_parsed_from_the_validator_strings():
    P = S.parse_limits
    assert P(["0.85 <= x <= 1.15"]) == (0.85, 1.15)
    assert P(["x <= 20"]) == (None, 20.0)
    assert P(["5 <= x"]) == (5.0, None)
    assert P(["x == 100"]) == (100.0, 100.0)
    assert P(["x == True"]) == (1.0, 1.0) and P(["x == False"]) == (0.0, 0.0)
    assert P(["-1e-09 <= x <= 1000000.0"]) == (-1e-09, 1000000.0)
    assert P(["0 <= Marginal:1 <= x <= Marginal:9 <= 10"]) == (0.0, 10.0)
    assert P(["'x' is within 5% of 10."]) == (9.5, 10.5)
    assert P(["'x' matches /^Ezi/"]) == (None, None) and P([]) == (None, None)
    assert P(["0 <= x <= 10", "x <= 8", "2 <= x"]) == (2.0, 8.0)  # several: the tightest


def test_a_run_is_stored_with_every_measurement(db):
    ids = store_known(db)
    assert sorted(ids) == list(range(1, 10))
    with S.open_store(db) as st:
        assert st.schema_version() == S.SCHEMA_VERSION
        r = st.run(ids[-1])  # the last stored: KNOWN[0], DUT A
        assert (r["plan"], r["plan_version"], r["plan_hash"], r["dut"], r["station"], r["operator"], r["verdict"]) == \
            ("eol", "1.0", "ab" * 32, "A", "st1", "anna", "PASS")
        assert r["drive"] == {"slave": 2, "protocol": 6, "slave_type": 20, "name": "Ezi-STEP"}
        assert r["start_ms"] == T0_MS and r["end_ms"] == T0_MS + 400 and r["files"] == {"json": "/r/run0.json"}
        assert [(p["name"], p["outcome"]) for p in r["phases"]] == [("preflight", "PASS"), ("identify", "FAIL"),
                                                                     ("move", "PASS"), ("home", "PASS")]
        ms = {m["name"]: m for p in r["phases"] for m in p["measurements"]}
        assert ms["duration_ratio"] == {"name": "duration_ratio", "value": 1.0, "text": "1.0", "unit": None,
                                        "low": 0.85, "high": 1.15, "limits": "0.85 <= x <= 1.15", "outcome": "PASS"}
        assert (ms["following_error"]["value"], ms["following_error"]["text"], ms["following_error"]["unit"],
                ms["following_error"]["low"], ms["following_error"]["high"]) == (2.0, "2", "pulse", None, 20.0)
        assert (ms["origin_ok"]["value"], ms["origin_ok"]["text"]) == (1.0, "True")
        assert (ms["slave_name"]["value"], ms["slave_name"]["text"], ms["slave_name"]["low"]) == \
            (None, "Ezi-STEP Plus-R", None)
        assert (ms["motor"]["value"], ms["motor"]["text"], ms["motor"]["outcome"]) == (None, None, "UNSET")
        assert ms["torque"]["unit"] == "N·cm"
        assert st.run(ids[0])["details"] == ""
        assert st.run(ids[4])["details"] == "lost"  # KNOWN[4], the ERROR run
        # the same record again is the same run, not a second one
        assert st.add_run(known_record(0)) == ids[-1]
        assert len(st.runs(limit=0)) == 9
        assert st.run(999) is None


def test_a_cia402_run_is_stored_with_its_node_and_identity(db, capsys):
    rec = record("node5-00000402-53490005", "PASS", T0_MS, [("identify", [meas("device_type", 0x20192)])],
                 plan="cia402-smoke")
    rec["metadata"]["drive"] = {"protocol": "cia402", "node_id": 5, "bitrate": 500000, "eds": "motorjig-cia402.eds",
                                "device_type": 0x20192, "vendor_id": 0x4D4A4947, "product_code": 0x402,
                                "revision": 0x10000, "serial": 0x53490005}
    with S.open_store(db) as st:
        run_id = st.add_run(rec)
        d = st.run(run_id)["drive"]
    assert d == {"slave": 5, "protocol": 402, "slave_type": 0x20192,
                 "name": "vendor 0x4D4A4947 product 0x00000402 rev 0x00010000 serial 0x53490005"}
    code, out, err = jigctl(capsys, "results", "--db", db, "show", str(run_id))
    assert code == 0, err
    assert "drive: CiA 402, CAN node 5, device type 0x00020192 (vendor 0x4D4A4947" in out


def test_yield_and_cpk_against_the_numbers_worked_out_by_hand(db):
    store_known(db)
    with S.open_store(db) as st:
        assert st.yield_("eol") == {"plan": "eol", "runs": 9, "duts": 5, "first_pass": 2, "final_pass": 3,
                                    "first_pass_yield": 0.4, "final_yield": 0.6}
        assert st.yield_("nothing")["duts"] == 0 and st.yield_("nothing")["first_pass_yield"] is None
        stats = {(s["step"], s["measurement"]): s for s in st.stats("eol")}
    assert set(stats) == set(EXPECTED_STATS)  # text-only and unset measurements have no statistics
    for key, want in EXPECTED_STATS.items():
        got = stats[key]
        for field, value in want.items():
            if value is None or isinstance(value, int):
                assert got[field] == value, (key, field)
            else:
                assert got[field] == pytest.approx(value, rel=1e-12, abs=1e-15), (key, field)
    assert stats[("move", "following_error")]["unit"] == "pulse"
    assert stats[("move", "duration_ratio")]["limits"] == "0.85 <= x <= 1.15"


def test_cpk_is_one_sided_and_none_without_spread_or_limits():
    assert S.cpk(6.0, 2.0, None, 20.0) == pytest.approx(14 / 6)
    assert S.cpk(6.0, 2.0, 0.0, None) == pytest.approx(1.0)
    assert S.cpk(6.0, 2.0, 0.0, 20.0) == pytest.approx(1.0)  # the nearer limit
    assert S.cpk(6.0, 0.0, 0.0, 20.0) is None and S.cpk(6.0, None, 0.0, 20.0) is None
    assert S.cpk(6.0, 2.0, None, None) is None


def test_a_tiny_spread_on_a_large_mean_keeps_its_digits(tmp_path):
    # 1e9 + 0.001 k: one pass over sums of squares would lose every digit of the spread
    runs = [record("X%d" % k, "PASS", T0_MS + k, [("p", [meas("big", 1e9 + 0.001 * k, ["x <= 2000000000"])])])
            for k in range(5)]
    with S.open_store(str(tmp_path / "big.sqlite")) as st:
        st.add_runs(runs)
        (s,) = st.stats("eol")
    # values 1e9 + (0, 1, 2, 3, 4) e-3: mean 1e9 + 0.002, sample variance 10e-6 / 4 = 2.5e-6
    assert s["sigma"] == pytest.approx(0.0015811388300841897, rel=1e-3)  # the values carry ~1e-7 of rounding


def test_filters_of_the_run_list(db):
    store_known(db)
    with S.open_store(db) as st:
        assert [r["id"] for r in st.runs(limit=3)] == [1, 2, 3]  # newest first: KNOWN[8], [7], [6]
        assert [r["verdict"] for r in st.runs(dut="B")] == ["PASS", "FAIL"]
        assert len(st.runs(verdict="fail")) == 4 and len(st.runs(verdict="FAIL", dut="C")) == 2
        assert st.runs(plan="other") == [] and len(st.runs(plan="eol")) == 9
        # runs at 08:00 .. 16:00 local on 2026-11-02
        assert len(st.runs(since="2026-11-02", until="2026-11-02")) == 9
        assert st.runs(since="2026-11-03") == [] and st.runs(until="2026-11-01") == []
        assert [r["dut"] for r in st.runs(since="2026-11-02 14:00")] == ["E", "D", "C"]
        assert [r["dut"] for r in st.runs(until=T0 + datetime.timedelta(hours=1))] == ["B", "A"]
        with pytest.raises(S.StoreError, match="is not a time"):
            st.runs(since="next tuesday")


def test_the_run_list_of_one_station(db):
    """A line's shared database: one station's runs, however many the others stored after them."""
    mine = [record("M%d" % k, "PASS", T0_MS + k, [("move", [])], station="desk-1") for k in range(3)]
    others = [record("O%d" % k, "FAIL", T0_MS + 1000 + k, [("move", [])], station="st%d" % (k % 3))
              for k in range(250)]
    with S.open_store(db) as st:
        st.add_runs(mine + others)
        assert len(st.runs(limit=200)) == 200 and all(r["station"] != "desk-1" for r in st.runs(limit=200))
        got = st.runs(station="desk-1", limit=12)
        assert [r["dut"] for r in got] == ["M2", "M1", "M0"] and {r["station"] for r in got} == {"desk-1"}
        assert [r["dut"] for r in st.runs(station="desk-1", limit=2)] == ["M2", "M1"]
        assert len(st.runs(station="st1", verdict="FAIL", limit=0)) == 83
        assert st.runs(station="nobody") == [] and st.runs(station="desk-1", verdict="FAIL") == []


# --- jigctl results: the same answers from SQLite and PostgreSQL -----------------------------------

def same(a, b, path="$"):
    """Equal, floats to 1e-9 (the two servers may add up in another order)."""
    if isinstance(a, float) or isinstance(b, float):
        assert a == pytest.approx(b, rel=1e-9, abs=1e-12), path
    elif isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            same(a[k], b[k], "%s.%s" % (path, k))
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            same(x, y, "%s[%d]" % (path, i))
    else:
        assert a == b, path


def test_jigctl_results_answers_the_same_from_sqlite_and_postgresql(pg, tmp_path, capsys):
    dbs = [str(tmp_path / "line.sqlite"), pg.create_database("line")]
    answers = []
    for d in dbs:
        store_known(d)
        got = {}
        for name, argv in [("list", ["list"]), ("list_c", ["list", "--dut", "C", "--verdict", "fail"]),
                           ("list_day", ["list", "--since", "2026-11-02 12:00", "--until", "2026-11-02 15:00"]),
                           ("show", ["show", "9"]), ("yield", ["yield", "--plan", "eol"]),
                           ("stats", ["stats", "--plan", "eol"])]:
            code, out, err = jigctl(capsys, "results", *argv, "--db", d, "--json")
            assert code == 0 and err == "", (name, err)
            doc = json.loads(out)
            doc.pop("db", None)
            doc.pop("stored", None)  # when it was stored
            code, text_out, err = jigctl(capsys, "results", "--db", d, *argv)
            assert code == 0 and err == ""
            got[name] = (doc, text_out)
        csv_path = str(tmp_path / ("export%d.csv" % len(answers)))
        code, out, err = jigctl(capsys, "--json", "results", "export", "--csv", csv_path, "--plan", "eol", "--db", d)
        assert code == 0 and json.loads(out)["rows"] == 9 * 8
        with open(csv_path, encoding="utf-8") as f:
            got["csv"] = f.read()
        answers.append(got)
    sq, pq = answers
    for name in sq:
        if name == "csv":
            assert sq["csv"] == pq["csv"]
            continue
        same(sq[name][0], pq[name][0], name)
        assert sq[name][1] == pq[name][1], name  # the text too
    # and what the answers are
    lst = sq["list"][0]["runs"]
    assert [r["dut"] for r in lst] == ["E", "D", "C", "B", "E", "D", "C", "B", "A"]
    assert [r["dut"] for r in sq["list_c"][0]["runs"]] == ["C", "C"]
    assert [r["dut"] for r in sq["list_day"][0]["runs"]] == ["D", "C", "B", "E"]  # 12:00 .. 15:00
    assert sq["show"][0]["dut"] == "A" and sq["show"][0]["phases"][2]["measurements"][1]["text"] == "2"
    words = " ".join(sq["yield"][1].split())
    assert "plan eol: 5 DUTs, 9 runs" in words
    assert "first-pass yield 40.0 % (2 of 5 DUTs passed the first run)" in words
    assert "final yield 60.0 % (3 of 5 DUTs passed the last run)" in words
    assert sq["stats"][0]["stats"][0]["cpk"] == pytest.approx(1.8257418583505536)
    stats_line = next(l for l in sq["stats"][1].splitlines() if "duration_ratio" in l)
    assert stats_line.split() == ["move", "duration_ratio", "9", "0.96", "1", "1.04", "0.02739", "0.85", "1.15",
                                  "1.83"]
    header, first = sq["csv"].splitlines()[:2]
    assert header.startswith("run_id,start,plan,plan_version,plan_hash,dut,station,operator,verdict,step,measurement,")
    assert first.split(",")[5] == "A" and first.split(",")[10] == "slave_name"


def test_jigctl_results_errors_are_one_sentence(tmp_path, capsys):
    d = str(tmp_path / "e.sqlite")
    store_known(d)
    cases = [
        (["show", "99"], "no run 99 in"),
        (["yield", "--plan", "nope"], "no runs of plan 'nope' in"),
        (["stats", "--plan", "nope"], "(plans there: eol)"),
        (["list", "--since", "2026-13-45"], "is not a time"),
        (["export", "--csv", str(tmp_path / "no" / "such" / "x.csv")], "cannot write"),
        (["import", str(tmp_path / "missing.json")], "cannot read"),
    ]
    for argv, words in cases:
        code, out, err = jigctl(capsys, "results", *argv, "--db", d)
        assert code == 2 and out == "" and words in err, (argv, err)
        assert err.startswith("jigctl: ") and err.count("\n") == 1 and "Traceback" not in err
    for bad in ("mysql://u@h/db", "postgresql://u@127.0.0.1:1/x", str(tmp_path)):
        code, out, err = jigctl(capsys, "results", "list", "--db", bad)
        assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    not_db = tmp_path / "notes.sqlite"
    not_db.write_bytes(b"these are not the tables you are looking for" * 100)
    code, out, err = jigctl(capsys, "results", "list", "--db", str(not_db))
    assert code == 2 and "is not a SQLite database" in err
    code, out, err = jigctl(capsys, "results", "show", "x1", "--db", d)
    assert code == 2 and "a run id is a number" in err
    for argv in (["results", "--help"], ["results", "export", "--help"]):
        code, out, err = jigctl(capsys, *argv)
        assert code == 0 and "--db PATH|URL" in out


def test_jigctl_results_import_stores_records_once(tmp_path, capsys):
    d = str(tmp_path / "i.sqlite")
    paths = []
    for k in range(3):
        p = tmp_path / ("rec%d.json" % k)
        p.write_text(json.dumps(known_record(k)))
        (tmp_path / ("rec%d.html" % k)).write_text("<html></html>")
        paths.append(str(p))
    code, out, err = jigctl(capsys, "--json", "results", "import", paths[0], paths[0], "--db", d)
    assert code == 0 and json.loads(out)["run_ids"] == [1, 1]  # twice in one batch: one run
    code, out, err = jigctl(capsys, "--json", "results", "import", *paths, "--db", d)
    assert code == 0 and json.loads(out)["run_ids"] == [1, 2, 3]
    code, out, err = jigctl(capsys, "--json", "results", "import", paths[1], "--db", d)
    assert json.loads(out)["run_ids"] == [2]
    with S.open_store(d) as st:
        assert len(st.runs()) == 3
        assert st.run(2)["files"] == {"html": str(tmp_path / "rec1.html"), "json": paths[1]}


# --- multi-up: the runs of a fixture's slots ---------------------------------------------------------
#
# Plan "multi" on station "mu1", four cycles of a two-slot fixture (both slots start in the same
# millisecond) and one run from before multi-up (no slot). Slot 2 has a bad contact: worse yield,
# a wider torque spread.
#
#   slot  runs (cycle 0..3)            torque          runs pass fail error  yield
#   1     PASS  PASS  PASS  FAIL       10 11  9 10     4    3    1    0      0.75
#   2     PASS  FAIL  ERROR FAIL        8 12  6 14     4    1    2    1      0.25
#   -     PASS (the earlier run)       10              1    1    0    0      1.0
#
# torque, limits 5 <= x <= 15 (Cpk = 5 / 3 sigma, every mean is 10):
#   slot 1: squares 0+1+1+0 = 2, variance 2/3, sigma 0.816496580927726, Cpk 2.041241452319315
#   slot 2: squares 4+4+16+16 = 40, variance 40/3, sigma 3.6514837167011076, Cpk 0.45643546458763845
#   no slot: n 1, no sigma, no Cpk; all 9: squares 42, variance 42/8, sigma 2.29128784747792,
#   Cpk 0.727392967453308. Each run is its own DUT: first-pass yield 5/9, runs of slot 2's DUTs 1/4.
MULTI = [  # cycle, slot, dut, verdict, torque
    (0, "1", "S1-0", "PASS", 10), (0, "2", "S2-0", "PASS", 8),
    (1, "1", "S1-1", "PASS", 11), (1, "2", "S2-1", "FAIL", 12),
    (2, "1", "S1-2", "PASS", 9), (2, "2", "S2-2", "ERROR", 6),
    (3, "1", "S1-3", "FAIL", 10), (3, "2", "S2-3", "FAIL", 14),
]
SLOT_YIELD = [{"slot": "1", "runs": 4, "pass": 3, "fail": 1, "error": 0, "yield": 0.75},
              {"slot": "2", "runs": 4, "pass": 1, "fail": 2, "error": 1, "yield": 0.25},
              {"slot": None, "runs": 1, "pass": 1, "fail": 0, "error": 0, "yield": 1.0}]
SLOT_TORQUE = {"1": (4, 10.0, 0.816496580927726, 2.041241452319315),  # n, mean, sigma, Cpk
               "2": (4, 10.0, 3.6514837167011076, 0.45643546458763845),
               None: (1, 10.0, None, None)}


def multi_records():
    out = []
    for cycle, slot, dut, verdict, torque in MULTI:
        rec = record(dut, verdict, T0_MS + cycle * 60000, [
            ("identify", [meas("slave_name", "Ezi-STEP Plus-R")]),
            ("move", [meas("torque", torque, ["5 <= x <= 15"], "N·cm")])], plan="multi", station="mu1")
        rec["metadata"]["slot"] = slot
        out.append(rec)
    out.append(record("U1", "PASS", T0_MS - 3600000, [("move", [meas("torque", 10, ["5 <= x <= 15"], "N·cm")])],
                      plan="multi", station="mu1"))  # the station before it was multi-up: no "slot"
    return out


def test_a_run_keeps_its_slot(db):
    recs = multi_records()
    with S.open_store(db) as st:
        one = st.add_run(recs[3])  # S2-1, slot "2"
        ids = st.add_runs(recs)    # the same run again keeps its id
        assert ids[3] == one and len(set(ids)) == 9
        assert st.run(one)["slot"] == "2" and st.run(ids[-1])["slot"] is None
        assert {r["dut"]: r["slot"] for r in st.runs(limit=0)} == dict(
            [(dut, slot) for _, slot, dut, _, _ in MULTI] + [("U1", None)])
        # both slots of a cycle started in the same millisecond: two runs, not one
        assert [r["dut"] for r in st.runs(slot="2", limit=0)] == ["S2-3", "S2-2", "S2-1", "S2-0"]
        assert [r["dut"] for r in st.runs(slot="1", verdict="FAIL")] == ["S1-3"]
        assert st.slots() == {"1": 4, "2": 4} and st.slots(plan="eol") == {}
        # what a record may carry as its slot: text as it is (trimmed), a number as text, nothing as no slot
        for value, kept in ((" A3 ", "A3"), (10, "10"), ("", None), (None, None)):
            rec = record("X-%r" % (value,), "PASS", T0_MS + 7, [("move", [])], plan="odd")
            rec["metadata"]["slot"] = value
            assert st.run(st.add_run(rec))["slot"] == kept, value
        assert list(st.slots()) == ["1", "2", "10", "A3"]  # by number, then by name
    assert sorted(["A10", "B1", "10", "2", "A3", None, "1"], key=S.slot_key) == ["1", "2", "10", "A3", "A10", "B1",
                                                                                  None]


def test_yield_and_cpk_per_slot_against_the_numbers_worked_out_by_hand(db):
    with S.open_store(db) as st:
        for rec in multi_records():
            st.add_run(rec)
        assert st.yield_by_slot("multi") == SLOT_YIELD
        assert st.yield_by_slot("multi", slot="2") == SLOT_YIELD[1:2]
        # the whole as before; one slot's DUTs alone
        y = st.yield_("multi")
        assert (y["runs"], y["duts"], y["first_pass"], y["final_pass"]) == (9, 9, 5, 5) and "slot" not in y
        assert st.yield_("multi", slot="2") == {"plan": "multi", "slot": "2", "runs": 4, "duts": 4, "first_pass": 1,
                                                "final_pass": 1, "first_pass_yield": 0.25, "final_yield": 0.25}
        (whole,) = st.stats("multi")
        assert (whole["n"], whole["sigma"], whole["cpk"]) == (9, pytest.approx(2.29128784747792),
                                                              pytest.approx(0.727392967453308))
        per = st.stats_by_slot("multi")
        assert [p["slot"] for p in per] == ["1", "2", None]
        for p in per:
            n, mean, sigma, cpk_ = SLOT_TORQUE[p["slot"]]
            assert (p["step"], p["measurement"], p["unit"], p["low"], p["high"]) == ("move", "torque", "N·cm", 5, 15)
            assert p["n"] == n and p["mean"] == pytest.approx(mean)
            assert p["sigma"] == (None if sigma is None else pytest.approx(sigma, rel=1e-12))
            assert p["cpk"] == (None if cpk_ is None else pytest.approx(cpk_, rel=1e-12))
        assert (per[1]["min"], per[1]["max"]) == (6, 14)
        (two,) = st.stats("multi", slot="2")
        assert two == {k: v for k, v in per[1].items() if k != "slot"}
        assert st.stats_by_slot("multi", slot="1") == per[:1]
        assert st.stats_by_slot("eol") == [] and st.yield_by_slot("eol") == []


def test_jigctl_results_by_slot_answers_the_same_from_sqlite_and_postgresql(pg, tmp_path, capsys):
    paths = []
    for k, rec in enumerate(multi_records()):
        paths.append(str(tmp_path / ("m%d.json" % k)))
        with open(paths[-1], "w") as f:
            json.dump(rec, f)
    answers = []
    for d in (str(tmp_path / "mu.sqlite"), pg.create_database("mu")):
        code, out, err = jigctl(capsys, "results", "--db", d, "import", *paths)  # add_runs carries the slot
        assert code == 0, err
        got = {}
        for name, argv in [("yield", ["yield", "--plan", "multi", "--by", "slot"]),
                           ("stats", ["stats", "--plan", "multi", "--by", "slot"]),
                           ("yield2", ["yield", "--plan", "multi", "--slot", "2"]),
                           ("stats2", ["stats", "--plan", "multi", "--slot", "2"]),
                           ("list2", ["list", "--slot", "2"]), ("list_u", ["list", "--dut", "U1"]),
                           ("show", ["show", "4"])]:
            code, out, err = jigctl(capsys, "results", "--db", d, *argv, "--json")
            assert code == 0 and err == "", (name, err)
            doc = json.loads(out)
            doc.pop("db", None)
            doc.pop("stored", None)
            code, text_out, err = jigctl(capsys, "results", "--db", d, *argv)
            assert code == 0 and err == "", (name, err)
            got[name] = (doc, text_out)
        csv_path = str(tmp_path / ("mu%d.csv" % len(answers)))
        code, out, err = jigctl(capsys, "results", "--db", d, "export", "--csv", csv_path, "--slot", "2")
        assert code == 0, err
        with open(csv_path, encoding="utf-8") as f:
            got["csv"] = f.read()
        code, out, err = jigctl(capsys, "results", "--db", d, "export", "--csv", "-", "--plan", "multi")
        got["csv_all"] = out
        answers.append(got)
    sq, pq = answers
    for name in sq:
        if name.startswith("csv"):
            assert sq[name] == pq[name], name
        else:
            same(sq[name][0], pq[name][0], name)
            assert sq[name][1] == pq[name][1], name

    y, text_y = sq["yield"]
    assert y["by_slot"] == SLOT_YIELD and (y["runs"], y["duts"], y["first_pass"]) == (9, 9, 5)
    rows = {line.split()[0]: line.split()[1:] for line in text_y.splitlines()[5:]}
    assert rows["slot"] == ["runs", "pass", "fail", "error", "yield"]
    assert rows["1"] == ["4", "3", "1", "0", "75.0", "%"] and rows["2"] == ["4", "1", "2", "1", "25.0", "%"]
    assert rows["-"] == ["1", "1", "0", "0", "100.0", "%"] and rows["all"] == ["9", "5", "3", "1", "55.6", "%"]
    assert "first-pass yield 55.6 % (5 of 9 DUTs passed the first run)" in " ".join(text_y.split())

    stats, text_s = sq["stats"]
    assert [(p["slot"], p["n"]) for p in stats["by_slot"]] == [("1", 4), ("2", 4), (None, 1)]
    assert stats["by_slot"][1]["cpk"] == pytest.approx(0.45643546458763845)
    lines = [ln.split() for ln in text_s.splitlines()]
    assert lines[0] == ["step", "measurement", "slot", "n", "min", "mean", "max", "sigma", "LSL", "USL", "Cpk",
                        "unit"]
    assert lines[1:] == [["move", "torque", "all", "9", "6", "10", "14", "2.291", "5", "15", "0.727", "N·cm"],
                         ["move", "torque", "1", "4", "9", "10", "11", "0.8165", "5", "15", "2.04", "N·cm"],
                         ["move", "torque", "2", "4", "6", "10", "14", "3.651", "5", "15", "0.456", "N·cm"],
                         ["move", "torque", "-", "1", "10", "10", "10", "-", "5", "15", "-", "N·cm"]]

    assert sq["yield2"][0]["slot"] == "2" and sq["yield2"][0]["first_pass_yield"] == 0.25
    assert "plan multi, slot 2: 4 DUTs, 4 runs" in sq["yield2"][1]
    assert sq["stats2"][0]["slot"] == "2" and sq["stats2"][0]["stats"][0]["n"] == 4
    assert sq["stats2"][1].splitlines()[1].split()[:3] == ["move", "torque", "4"]

    # list: a slot column where a listed run has a slot, none where none has
    assert [r["slot"] for r in sq["list2"][0]["runs"]] == ["2"] * 4
    head = sq["list2"][1].splitlines()[0].split()
    # (the start time is two words)
    assert head[5:7] == ["station", "slot"] and all(ln.split()[7] == "2" for ln in sq["list2"][1].splitlines()[1:])
    assert sq["list_u"][0]["runs"][0]["slot"] is None and "slot" not in sq["list_u"][1].splitlines()[0].split()
    assert sq["show"][0]["slot"] == "2" and "dut S2-1, station mu1, slot 2, operator anna" in sq["show"][1]

    # the CSV: the slot is the last column, empty for the run that was no slot
    rows = [ln.split(",") for ln in sq["csv"].splitlines()]
    assert rows[0][-1] == "slot" and len(rows) == 1 + 4 * 2 and {r[-1] for r in rows[1:]} == {"2"}
    assert {r[5] for r in rows[1:]} == {"S2-0", "S2-1", "S2-2", "S2-3"}
    by_dut = {r[5]: r[-1] for r in (ln.split(",") for ln in sq["csv_all"].splitlines()[1:])}
    assert by_dut["U1"] == "" and by_dut["S1-0"] == "1"


def test_jigctl_results_slot_errors_are_one_sentence(tmp_path, capsys):
    d = str(tmp_path / "s.sqlite")
    with S.open_store(d) as st:
        st.add_runs(multi_records())
    for argv, words in [(["list", "--slot", "9"], "no runs in slot '9' in %s (slots there: 1, 2)" % d),
                        (["yield", "--plan", "multi", "--slot", "3"], "no runs in slot '3'"),
                        (["stats", "--plan", "multi", "--by", "dut"], "argument --by: invalid choice: 'dut'"),
                        (["yield", "--plan", "multi", "--slot", ""], "a slot is a fixture position's name"),
                        (["export", "--csv", "-", "--slot", "a b"], "a slot is a fixture position's name")]:
        code, out, err = jigctl(capsys, "results", "--db", d, *argv)
        assert code == 2 and out == "" and words in err and "Traceback" not in err, (argv, err)
        assert err.strip().splitlines()[-1].count(".") <= 2  # one sentence (argparse adds its usage above)
    # a database that was never multi-up: every slot is unknown, and it says so
    d2 = str(tmp_path / "k.sqlite")
    store_known(d2)
    code, out, err = jigctl(capsys, "results", "--db", d2, "list", "--slot", "1")
    assert code == 2 and "(slots there: none, no run was a slot)" in err
    # a known slot and a known plan that never met: an empty answer
    with S.open_store(d) as st:
        st.add_run(record("Z", "PASS", T0_MS, [("move", [])], plan="other", station="mu1"))
    code, out, err = jigctl(capsys, "results", "--db", d, "yield", "--plan", "other", "--slot", "1", "--by", "slot")
    assert code == 0 and "no runs of plan other in slot 1" in out, err
    code, out, err = jigctl(capsys, "results", "--db", d, "--json", "stats", "--plan", "other", "--slot", "1",
                            "--by", "slot")
    assert code == 0 and json.loads(out) == {"plan": "other", "slot": "1", "stats": [], "by_slot": []}


# --- two stations at once ---------------------------------------------------------------------------

def station_record(station, code, i):
    """Run i of a station: every value says whose it is."""
    dut = "%s-%03d" % (station, i)
    return record(dut, "PASS" if i % 7 else "FAIL", T0_MS + i * 1000, [
        ("identify", [meas("tag", dut), meas("station_code", code, ["x == %d" % code])]),
        ("move", [meas("index", i, ["0 <= x <= 1000"]), meas("ratio", 1 + i / 1000.0, ["0.85 <= x <= 1.15"]),
                  meas("check", code * 1000 + i)]),
    ], plan="conc", station=station)


def station_main(db, station, code, n, ready, go):
    """One station process: open the database (creating it, perhaps at the same moment as the
    other), say ready, wait for go, then store n runs, one transaction each."""
    st = S.open_store(db)
    with open(ready, "w") as f:
        f.write("ready")
    deadline = time.time() + 30
    while not os.path.exists(go) and time.time() < deadline:
        time.sleep(0.002)
    t0 = time.time()
    ids = [st.add_run(station_record(station, code, i)) for i in range(n)]
    t1 = time.time()
    st.close()
    print(json.dumps({"ids": ids, "t0": t0, "t1": t1}))


WORKER = ("import sys, json; sys.path[:0] = %r; import test_station_store as t; "
          "t.station_main(*json.loads(sys.argv[1]))")


def test_two_stations_writing_at_once_lose_nothing(db, tmp_path):
    n = 200
    go = str(tmp_path / "go")
    procs, readies = [], []
    for code, station in ((1, "S1"), (2, "S2")):
        ready = str(tmp_path / ("ready%d" % code))
        readies.append(ready)
        argv = json.dumps([db, station, code, n, ready, go])
        procs.append(subprocess.Popen([sys.executable, "-c", WORKER % [HERE, os.path.join(ROOT, "tools"),
                                                                       os.path.join(ROOT, "firmware")], argv],
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    deadline = time.time() + 30
    while not all(os.path.exists(r) for r in readies) and time.time() < deadline:
        time.sleep(0.005)
    with open(go, "w") as f:
        f.write("go")
    results = [p.communicate(timeout=120) for p in procs]
    for p, (out, err) in zip(procs, results):
        assert p.returncode == 0, err
    done = [json.loads(out) for out, _ in results]
    ids = [d["ids"] for d in done]
    assert len(set(ids[0]) | set(ids[1])) == 2 * n and not set(ids[0]) & set(ids[1])
    # both were writing at the same time (SQLite may let one wait for the other's lock all along)
    assert max(d["t0"] for d in done) < min(d["t1"] for d in done)

    eng = create_engine(S.resolve(db))
    with eng.connect() as c:
        runs = {r.id: r for r in c.execute(text("SELECT id, dut, station FROM runs"))}
        rows = c.execute(text("SELECT m.run_id, s.phase, s.name, m.value_num, m.value_text FROM measurements m "
                              "JOIN series s ON s.id = m.series_id")).all()
        n_phases = c.execute(text("SELECT count(*) FROM phases")).scalar()
    eng.dispose()
    assert len(runs) == 2 * n and len(rows) == 2 * n * 5 and n_phases == 2 * n * 2
    by_run = {}
    for run_id, phase, name, num, txt in rows:
        by_run.setdefault(run_id, {})[name] = (num, txt)
    for code, station in ((1, "S1"), (2, "S2")):
        for i, run_id in enumerate(ids[code - 1]):
            r, m = runs[run_id], by_run[run_id]
            assert (r.station, r.dut) == (station, "%s-%03d" % (station, i))
            assert m["tag"][1] == r.dut and m["station_code"][0] == code and m["index"][0] == i
            assert m["check"][0] == code * 1000 + i and m["ratio"][0] == pytest.approx(1 + i / 1000.0)
    with S.open_store(db) as st:
        y = st.yield_("conc")
        assert (y["duts"], y["runs"], y["first_pass"]) == (400, 400, 400 - 2 * 29)  # i % 7 == 0 fails: 29 of 200


# --- schema versions -------------------------------------------------------------------------------

def set_version(db, value):
    eng = create_engine(S.resolve(db))
    with eng.begin() as c:
        c.execute(text("UPDATE meta SET value = :v WHERE key = 'schema_version'"), {"v": str(value)})
    eng.dispose()


def test_a_newer_database_is_refused_and_left_as_it_is(db, capsys):
    store_known(db)
    set_version(db, S.SCHEMA_VERSION + 1)
    with pytest.raises(S.StoreError, match=r"schema version %d, newer than this motorjig knows \(%d\)"
                       % (S.SCHEMA_VERSION + 1, S.SCHEMA_VERSION)):
        S.open_store(db)
    code, out, err = jigctl(capsys, "results", "list", "--db", db)
    assert code == 2 and "newer than this motorjig knows" in err and "update motorjig" in err
    eng = create_engine(S.resolve(db))
    with eng.connect() as c:
        assert c.execute(text("SELECT value FROM meta WHERE key = 'schema_version'")).scalar() == \
            str(S.SCHEMA_VERSION + 1)
        assert c.execute(text("SELECT count(*) FROM runs")).scalar() == 9
    eng.dispose()


def test_an_older_database_is_upgraded_or_refused(db, monkeypatch):
    store_known(db)
    # an upgrade from this version to the next, as a future motorjig would carry it
    def add_serial_column(c):
        c.execute(text("ALTER TABLE runs ADD COLUMN board_serial TEXT"))
        c.execute(text("UPDATE runs SET board_serial = 'b-' || dut"))

    monkeypatch.setattr(S, "SCHEMA_VERSION", S.SCHEMA_VERSION + 1)
    monkeypatch.setattr(S, "MIGRATIONS", {S.SCHEMA_VERSION - 1: add_serial_column})
    with S.open_store(db) as st:
        assert st.schema_version() == S.SCHEMA_VERSION
        assert st.yield_("eol")["duts"] == 5  # the runs survived
    eng = create_engine(S.resolve(db))
    with eng.connect() as c:
        assert c.execute(text("SELECT board_serial FROM runs WHERE dut = 'A'")).scalar() == "b-A"
    eng.dispose()
    # a version no upgrade starts from: refused, untouched
    set_version(db, 0)
    with pytest.raises(S.StoreError, match="schema version 0, older than this motorjig can upgrade"):
        S.open_store(db)


def make_version_1(db):
    """Turn a database of this version back into what version 1 was: ``runs`` without the slot
    column and its index (the one difference of version 2), the version says 1."""
    eng = create_engine(S.resolve(db))
    with eng.begin() as c:
        c.execute(text("DROP INDEX runs_slot"))
        c.execute(text("ALTER TABLE runs DROP COLUMN slot"))
    eng.dispose()
    set_version(db, 1)


def runs_columns(db):
    eng = create_engine(S.resolve(db))
    with eng.connect() as c:
        from sqlalchemy import inspect
        cols = [col["name"] for col in inspect(c).get_columns("runs")]
        indexes = {ix["name"] for ix in inspect(c).get_indexes("runs")}
    eng.dispose()
    return cols, indexes


def test_a_version_1_database_is_upgraded_in_place_its_runs_no_slot(db, capsys):
    assert S.SCHEMA_VERSION == 2
    store_known(db)
    make_version_1(db)
    cols, indexes = runs_columns(db)
    assert "slot" not in cols and "runs_slot" not in indexes
    code, out, err = jigctl(capsys, "results", "--db", db, "list", "--limit", "1")  # a read upgrades it too
    assert code == 0 and "slot" not in out.splitlines()[0], err
    cols, indexes = runs_columns(db)
    assert cols[-1] == "slot" and "runs_slot" in indexes
    with S.open_store(db) as st:
        assert st.schema_version() == 2
        assert [r["slot"] for r in st.runs(limit=0)] == [None] * 9  # the old rows: not slots
        assert st.yield_("eol")["first_pass"] == 2 and st.run(9)["slot"] is None
        assert st.yield_by_slot("eol") == [{"slot": None, "runs": 9, "pass": 4, "fail": 4, "error": 1,
                                            "yield": 4 / 9}]
        ids = st.add_runs(multi_records())  # and new runs keep theirs
        assert st.run(ids[0])["slot"] == "1" and st.yield_by_slot("multi") == SLOT_YIELD


def test_a_failed_upgrade_leaves_the_old_database(tmp_path, monkeypatch):
    d = str(tmp_path / "u.sqlite")
    store_known(d)

    def broken(c):
        c.execute(text("ALTER TABLE runs ADD COLUMN half TEXT"))
        raise RuntimeError("power cut")

    monkeypatch.setattr(S, "SCHEMA_VERSION", S.SCHEMA_VERSION + 1)
    monkeypatch.setattr(S, "MIGRATIONS", {S.SCHEMA_VERSION - 1: broken})
    with pytest.raises(S.StoreError, match="upgrading .* from schema version %d to %d failed .*power cut"
                       % (S.SCHEMA_VERSION - 1, S.SCHEMA_VERSION)):
        S.open_store(d)
    eng = create_engine(S.resolve(d))
    with eng.connect() as c:
        assert c.execute(text("SELECT value FROM meta WHERE key = 'schema_version'")).scalar() == \
            str(S.SCHEMA_VERSION - 1)
        cols = [r[1] for r in c.execute(text("PRAGMA table_info(runs)"))]
    eng.dispose()
    assert "half" not in cols  # the upgrade ran in one transaction


def test_a_database_of_something_else_is_refused(tmp_path):
    d = str(tmp_path / "other.sqlite")
    eng = create_engine("sqlite:///" + d)
    with eng.begin() as c:
        c.execute(text("CREATE TABLE runs (x INTEGER)"))
    eng.dispose()
    with pytest.raises(S.StoreError, match="no 'meta' table with a schema version: not a MotorJig"):
        S.open_store(d)


def test_the_default_database_is_in_the_users_data_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    assert S.default_path() == str(tmp_path / "data" / "motorjig" / "results.sqlite")
    with S.open_store() as st:
        assert st.name == S.default_path()
    assert os.path.exists(S.default_path())
    monkeypatch.delenv("XDG_DATA_HOME")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert S.default_path() == str(tmp_path / ".local" / "share" / "motorjig" / "results.sqlite")
    assert S.resolve("postgresql://u@h/motorjig").drivername == "postgresql+psycopg"


# --- jigctl test stores its runs -------------------------------------------------------------------

def test_jigctl_test_stores_each_run_and_reports_a_failure_to(tmp_path, capsys, monkeypatch):
    from motorjig.sim import Bench

    d = str(tmp_path / "station.sqlite")
    with Bench(driver_ids=(2,), baud=115200, pty=False) as b:
        base = ["test", SMOKE, "--port", b.tcp_url, "--yes", "--json"]
        code, out, err = jigctl(capsys, *base, "--out", str(tmp_path / "a"), "--db", d)
        assert code == 0, err
        res = json.loads(out)
        assert res["db"] == {"db": d, "run_id": 1, "error": None}
        with S.open_store(d) as st:
            r = st.run(1)
        assert r["plan"] == "smoke" and r["verdict"] == "PASS" and r["plan_hash"] == res["plan_hash"]
        assert r["files"] == {k: os.path.abspath(v) for k, v in res["files"].items()}
        assert [p["name"] for p in r["phases"]] == ["preflight", "identify", "servo", "out", "back", "servo_off"]
        out_m = {m["name"]: m for m in r["phases"][3]["measurements"]}
        assert out_m["position_error"]["value"] == 0 and out_m["following_error"]["high"] == 10

        # the database fails while the run is stored: the verdict stands, the files are there, it is said
        def refuse(self, record, files=None):
            raise S.StoreError("database error in %s: disk I/O error" % self.name)

        monkeypatch.setattr(S.Store, "add_run", refuse)
        code, out, err = jigctl(capsys, *base, "--out", str(tmp_path / "b"), "--db", d)
        res = json.loads(out)
        assert code == 0 and res["verdict"] == "PASS"
        assert res["db"]["run_id"] is None and "disk I/O error" in res["db"]["error"]
        assert "the run was not stored" in err and "jigctl results import" in err and err.count("\n") == 1
        assert all(os.path.exists(p) for p in res["files"].values())
        monkeypatch.undo()

        # --db none stores nothing; a bad --db is refused before anything moves
        code, out, err = jigctl(capsys, *base, "--out", str(tmp_path / "c"), "--db", "none")
        assert code == 0 and "db" not in json.loads(out)
        code, out, err = jigctl(capsys, *base, "--out", str(tmp_path / "d"), "--db", "mysql://x/y")
        assert code == 2 and "--db none" in err and not os.path.exists(tmp_path / "d")
    with S.open_store(d) as st:
        assert len(st.runs()) == 1


# --- what a user's report found ---------------------------------------------------------------------

READS = [["list"], ["show", "1"], ["yield", "--plan", "eol"], ["stats", "--plan", "eol"],
         ["export", "--csv", "OUT"]]


def test_a_database_that_is_not_there_is_refused_by_every_command_that_only_reads(tmp_path, capsys):
    missing = tmp_path / "typo" / "x.sqlite"
    for argv in READS:
        argv = [str(tmp_path / "out.csv") if a == "OUT" else a for a in argv]
        code, out, err = jigctl(capsys, "results", "--db", str(missing), *argv)
        assert code == 2 and out == "", (argv, out)
        assert err.startswith("jigctl: there is no results database %s" % missing) and err.count("\n") == 1, err
        assert not (tmp_path / "typo").exists() and not (tmp_path / "out.csv").exists()
    # import writes: it creates the database
    rec = tmp_path / "rec.json"
    rec.write_text(json.dumps(known_record(0)))
    code, out, err = jigctl(capsys, "results", "--db", str(missing), "import", str(rec))
    assert code == 0 and missing.exists(), err
    code, out, err = jigctl(capsys, "results", "--db", str(missing), "list")
    assert code == 0 and "eol" in out


def test_an_empty_database_is_refused_by_reads_and_left_empty(db, capsys):
    if "://" not in db:  # a SQLite file that exists but holds nothing of ours
        create_engine("sqlite:///" + db).connect().close()
    code, out, err = jigctl(capsys, "results", "--db", db, "list")
    assert code == 2 and "holds no MotorJig results" in err and err.count("\n") == 1, err
    engine = create_engine(S.resolve(db))
    try:
        with engine.connect() as c:
            assert c.execute(text("SELECT 1")).scalar() == 1
            from sqlalchemy import inspect
            assert inspect(c).get_table_names() == []  # nothing was created
    finally:
        engine.dispose()


@pytest.mark.parametrize("argv", [["list"], ["export", "--csv", "OUT"], ["yield"], ["stats"]])
def test_one_rule_a_plan_or_dut_the_database_does_not_know_is_refused(tmp_path, capsys, argv):
    d = str(tmp_path / "k.sqlite")
    store_known(d)
    argv = [str(tmp_path / "out.csv") if a == "OUT" else a for a in argv]
    code, out, err = jigctl(capsys, "results", "--db", d, *argv, "--plan", "nope")
    assert code == 2 and out == "" and "no runs of plan 'nope'" in err and "(plans there: eol)" in err, err
    assert not (tmp_path / "out.csv").exists()
    if argv[0] in ("list", "export"):
        code, out, err = jigctl(capsys, "results", "--db", d, *argv, "--dut", "ZZ")
        assert code == 2 and "no runs of DUT 'ZZ'" in err, err
        # known names whose filters leave nothing: an empty answer, exit 0
        code, out, err = jigctl(capsys, "results", "--db", d, *argv, "--plan", "eol", "--dut", "A",
                                "--verdict", "FAIL")
        assert code == 0 and err == "" and "no runs in" in out, (out, err)


def test_the_csv_export_keeps_runs_without_measurements(tmp_path, capsys):
    """A run refused at the preflight has no measurement; without a row of its own, yield computed
    from the CSV would miss it."""
    import csv

    d = str(tmp_path / "c.sqlite")
    store_known(d)
    refused = record("F", "ERROR", T0_MS + 20 * 3600000, [("preflight", [])])
    with S.open_store(d) as st:
        st.add_run(refused)
        y = st.yield_("eol")
    path = tmp_path / "all.csv"
    code, out, err = jigctl(capsys, "results", "--db", d, "export", "--csv", str(path), "--plan", "eol")
    assert code == 0, err
    with open(path, encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    last = rows[-1]
    assert last["dut"] == "F" and last["verdict"] == "ERROR" and last["step"] == last["measurement"] == ""
    assert len(rows) == 9 * 8 + 1
    runs = {}
    for r in rows:
        runs.setdefault(r["dut"], {})[(r["start"], r["run_id"])] = r["verdict"]
    first = sum(v[min(v)] == "PASS" for v in runs.values())
    final = sum(v[max(v)] == "PASS" for v in runs.values())
    assert (len(runs), first, final) == (y["duts"], y["first_pass"], y["final_pass"]) == (6, 2, 3)


def test_stats_prints_numbers_readably(tmp_path, capsys):
    from motorjig.resultscmd import _num

    assert [_num(v) for v in (134217727.0, 134217727, 1.0, 0.0, -3.0)] == ["134217727", "134217727", "1", "0", "-3"]
    assert [_num(v) for v in (134217727.5, 1250.25, 0.96, 1.0000001, 0.0273861, -12.3456789)] == \
        ["134217727.5", "1250.25", "0.96", "1", "0.0273861", "-12.3457"]
    assert _num(0.027386127875258306, 4) == "0.02739" and _num(1.8257418583505536, 3) == "1.83"
    assert _num(0.0000123456) == "1.23456e-05" and _num(None) == "-"
    d = str(tmp_path / "n.sqlite")
    with S.open_store(d) as st:
        for k, v in enumerate((134217727, 134217727, 134217728)):
            st.add_run(record("N%d" % k, "PASS", T0_MS + k * 1000,
                              [("move", [meas("position", v, ["x <= 2147483647"], "pulse")])]))
    code, out, err = jigctl(capsys, "results", "--db", d, "stats", "--plan", "eol")
    line = next(ln for ln in out.splitlines() if "position" in ln).split()
    assert line[:6] == ["move", "position", "3", "134217727", "134217727.3", "134217728"], out
    assert "e+" not in out


def test_a_run_without_an_operator_shows_unknown(tmp_path, capsys):
    """No --operator and $USER unset (a service): records keep what they got, every view says unknown."""
    from motorjig.station import junit, report

    rec = record("U1", "PASS", T0_MS, [("move", [meas("alarm", 0, ["x == 0"])])])
    rec["metadata"]["operator"] = ""
    d = str(tmp_path / "o.sqlite")
    with S.open_store(d) as st:
        run_id = st.add_run(rec)
        assert st.run(run_id)["operator"] == "unknown" and st.runs()[0]["operator"] == "unknown"
    code, out, err = jigctl(capsys, "results", "--db", d, "show", str(run_id))
    assert "operator unknown" in out
    path = tmp_path / "o.csv"
    jigctl(capsys, "results", "--db", d, "export", "--csv", str(path))
    assert path.read_text().splitlines()[1].split(",")[7] == "unknown"
    assert 'data-testid="info-operator">unknown<' in report.html_report(rec)
    assert '<property name="operator" value="unknown"' in junit.junit_xml(rec)
    # a database written before (operator '') reads as unknown too
    with S.open_store(d) as st, st.engine.begin() as c:
        c.execute(text("UPDATE runs SET operator = ''"))
    with S.open_store(d) as st:
        assert st.run(run_id)["operator"] == "unknown"
