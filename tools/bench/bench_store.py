"""Results-database benchmark (part of `make bench`): prints figures, asserts nothing.

Fills a SQLite file and a PostgreSQL database (a temporary cluster of Debian's server,
started like the tests' fixture by ``motorjig.station.pgtemp``, with the server's
durable defaults: fsync and synchronous commit on) with the history of a line: 100 000
runs of a 30-measurement plan (about 88 000 DUTs, every eighth run a retest, 5 %
failing). Then, on top of that history:

* one run stored the way a station stores it: ``Store.add_run``, its own transaction,
  committed to disk, timed one by one (mean and p95),
* ``yield_`` + ``stats`` of the plan: first-pass and final yield and n / min / mean /
  max / sigma / Cpk of all 30 measurements over the 100 000 runs.

Goals: <= 20 ms to store one run, <= 1 s for yield + every Cpk, on each database.
The history itself is built with bulk inserts (``Store.add_runs``, 1 000 runs per
transaction), which the output says; PostgreSQL then gets ``VACUUM ANALYZE``, which
autovacuum does on a server that runs for longer than this benchmark.
"""

import argparse
import os
import random
import shutil
import statistics
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
for sub in ("firmware", "tools"):
    p = os.path.join(ROOT, sub)
    if p not in sys.path:
        sys.path.insert(0, p)

from motorjig.station import store as S  # noqa: E402
from motorjig.station.pgtemp import ClusterError, TempCluster, find_bin  # noqa: E402

T0_MS = 1_790_000_000_000
PLAN = "bench-eol"


def _m(value, validators=(), unit=None, outcome="PASS"):
    m = {"outcome": outcome, "validators": list(validators), "measured_value": value}
    if unit:
        m["units"] = {"name": unit, "code": unit, "suffix": unit}
    return m


def make_record(k, rng):
    """Run k of the line: 30 measurements in 7 steps, like an EOL plan's."""
    dut = "SN%06d" % (k - k // 8)  # every eighth run retests the DUT before it
    fail = rng.random() < 0.05
    ms = {"identify": {"slave_type": _m(20, ["x == 20"]), "name_ok": _m(True, ["x == True"]),
                       "slave_name": _m("Ezi-STEP Plus-R ST v6.0")},
          "parameters": {"ram_p%d" % i: _m(100 + i, ["x == %d" % (100 + i)]) for i in range(5)}}
    for speed in (2000, 20000, 50000):
        ratio = rng.gauss(1.02, 0.02) + (0.2 if fail and speed == 50000 else 0.0)
        ms["move_speed_%d" % speed] = {
            "duration": _m(round(rng.gauss(0.4, 0.01), 4), unit="s"),
            "duration_ratio": _m(round(ratio, 4), ["0.85 <= x <= 1.15"],
                                 outcome="FAIL" if not 0.85 <= ratio <= 1.15 else "PASS"),
            "position_error": _m(0, ["x <= 0"], "pulse"),
            "following_error": _m(abs(int(rng.gauss(3, 2))), ["x <= 20"], "pulse"),
            "in_position": _m(True, ["x == True"]),
            "samples": _m(rng.randint(60, 70))}
    ms["bus-health"] = {"crc_errors": _m(0, ["x <= 0"]), "rt_mean": _m(round(rng.gauss(5.1, 0.2), 3), ["x <= 8"], "ms"),
                        "rt_max": _m(round(rng.gauss(6.5, 0.5), 3), ["x <= 15"], "ms"),
                        "holding_torque": _m(round(rng.gauss(42.0, 1.5), 2), ["35 <= x"], "N·cm")}
    phases, t = [], T0_MS + k * 60_000
    for name, meas in ms.items():
        for mname, m in meas.items():
            m["name"] = mname
        phases.append({"name": name, "outcome": "FAIL" if any(m["outcome"] == "FAIL" for m in meas.values())
                       else "PASS", "start_time_millis": t, "end_time_millis": t + 500, "measurements": meas})
        t += 500
    return {"dut_id": dut, "station_id": "line-%d" % (k % 4), "start_time_millis": T0_MS + k * 60_000,
            "end_time_millis": t, "outcome": "FAIL" if fail else "PASS",
            "metadata": {"test_name": PLAN, "test_version": "1.0", "plan_hash": "f" * 64, "operator": "bench",
                         "plan_file": "/plans/bench-eol.toml",
                         "drive": {"slave": 2, "protocol": 6, "slave_type": 20, "name": "Ezi-STEP"}},
            "phases": phases}


def pct(values, q):
    values = sorted(values)
    return values[min(len(values) - 1, int(round(q * (len(values) - 1))))]


def bench(label, db, runs, singles, batch, after_build=None):
    print("%s:" % label, flush=True)
    rng = random.Random(1)
    st = S.open_store(db)
    t0 = time.perf_counter()
    k = 0
    while k < runs:
        n = min(batch, runs - k)
        st.add_runs([make_record(k + i, rng) for i in range(n)])
        k += n
    build = time.perf_counter() - t0
    print("  history: %d runs x 30 measurements by bulk inserts (%d runs per transaction): %.1f s (%.2f ms/run)"
          % (runs, batch, build, 1000.0 * build / max(runs, 1)), flush=True)
    if after_build:
        t = time.perf_counter()
        after_build()
        print("  VACUUM ANALYZE after the bulk load: %.1f s" % (time.perf_counter() - t))
    times = []
    for i in range(singles):
        rec = make_record(runs + i, rng)
        t = time.perf_counter()
        st.add_run(rec, {"json": "/results/run%d.json" % i, "xml": "/results/run%d.xml" % i,
                         "html": "/results/run%d.html" % i})
        times.append(time.perf_counter() - t)
    print("  store one run (add_run, own transaction, %d runs on top of the history): mean %.2f ms, p95 %.2f ms, "
          "max %.2f ms   (goal <= 20 ms)" % (singles, 1000 * statistics.mean(times), 1000 * pct(times, 0.95),
                                             1000 * max(times)))
    query = []
    for _ in range(3):
        t = time.perf_counter()
        y = st.yield_(PLAN)
        stats = st.stats(PLAN)
        query.append(time.perf_counter() - t)
    with_cpk = sum(1 for s in stats if s["cpk"] is not None)
    print("  yield + stats of %d measurements (%d with a Cpk) over %d runs / %d DUTs: first %.3f s, best of 3 %.3f s"
          "   (goal <= 1 s)" % (len(stats), with_cpk, y["runs"], y["duts"], query[0], min(query)))
    print("    first-pass yield %.1f %%, final yield %.1f %%; e.g. Cpk of move_speed_2000 duration_ratio %.2f"
          % (100 * y["first_pass_yield"], 100 * y["final_yield"],
             next(s["cpk"] for s in stats if s["step"] == "move_speed_2000" and s["measurement"] == "duration_ratio")),
          flush=True)
    st.close()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100_000, help="runs in the history (default 100 000)")
    ap.add_argument("--singles", type=int, default=500, help="single-run inserts timed on top (default 500)")
    ap.add_argument("--batch", type=int, default=1000, help="runs per bulk transaction (default 1 000)")
    ap.add_argument("--only", choices=("sqlite", "postgresql"), help="one database only")
    ap.add_argument("--quick", action="store_true", help="a few seconds: the smallest sizes, one run each (make test runs it)")
    a = ap.parse_args(argv)
    if a.quick:
        a.runs, a.singles, a.batch = 200, 5, 100
    print("results database (SQLAlchemy Core; %d runs of a 30-measurement plan):" % a.runs)
    folder = tempfile.mkdtemp(prefix="bench-store-")
    try:
        if a.only != "postgresql":
            bench("SQLite (WAL, synchronous=FULL, on %s)" % folder, os.path.join(folder, "results.sqlite"), a.runs,
                  a.singles, a.batch)
        if a.only != "sqlite":
            if find_bin() is None:
                print("PostgreSQL: skipped, no server binaries (Debian: apt-get install postgresql)")
                return
            try:
                with TempCluster(fast=False) as pg:
                    url = pg.create_database("bench")
                    from sqlalchemy import create_engine, text

                    def vacuum():
                        eng = create_engine(S.resolve(url), isolation_level="AUTOCOMMIT")
                        with eng.connect() as c:
                            c.execute(text("VACUUM ANALYZE"))
                        eng.dispose()

                    version = pg.server_version()
                    bench("PostgreSQL %s (temporary cluster, fsync on, localhost TCP, psycopg 3)" % version, url,
                          a.runs, a.singles, a.batch, after_build=vacuum)
            except ClusterError as exc:
                print("PostgreSQL: skipped, %s" % exc)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
