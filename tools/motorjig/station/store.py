"""The station's results database: every run kept, queried for yield and process capability.

    store = open_store()                     # ~/.local/share/motorjig/results.sqlite
    store = open_store("postgresql://station@dbhost/motorjig")
    run_id = store.add_run(record, files={"json": ..., "xml": ..., "html": ...})
    store.runs(plan="smoke", verdict="FAIL", since="2026-12-01")
    store.yield_("smoke")                    # first-pass and final yield
    store.stats("smoke")                     # n, min, mean, max, sigma, Cpk per step + measurement
    store.yield_by_slot("smoke")             # runs, pass, fail, error, yield of each fixture slot
    store.stats_by_slot("smoke")             # stats per step + measurement per slot

One schema and one code path (SQLAlchemy Core) for SQLite, the default, one file per
computer, and PostgreSQL, one server for a line of stations (driver: psycopg 3). The
record is OpenHTF's JSON test record as ``jigctl test`` writes it (``station.runner``).

Tables: ``meta`` (the schema version), ``runs`` (plan name, version and hash, DUT,
station, slot, operator, drive, times, verdict), ``phases`` (each step's outcome), ``series``
(a measurement of a plan: step, name, unit, the validator text and the limits parsed
from it), ``measurements`` (one value of a series in a run: number and text, outcome)
and ``run_files`` (the record, JUnit XML and report written for the run).

A station that tests several drives at once (multi-up) runs each fixture position, a
*slot*, as its own run: the record's ``metadata["slot"]`` (a short name, "1", "A3") is kept
in ``runs.slot``, NULL for a run that was not a slot, so that yield and Cpk can be asked per
slot (``yield_by_slot``, ``stats_by_slot``) and a position with a bad contact shows.

The schema is created on first use and carries its version: an older database is
upgraded in one transaction (``MIGRATIONS``) or refused when no upgrade is known, a
newer one is always refused, so no version of jigctl writes rows another cannot read.
Each run is stored in one transaction. SQLite runs in WAL mode and takes the write
lock when a write transaction begins (``BEGIN IMMEDIATE``), waits for it (busy timeout)
and retries on "database is locked"; PostgreSQL needs nothing but its transactions.
Storing the same record twice returns the first run's id (runs are identified by plan,
DUT, start time and station), so a retried or re-imported run is not counted twice.

Every failure is a ``StoreError`` with one sentence that names the database.
"""

import csv
import datetime
import functools
import io
import json
import math
import os
import random
import re
import time

from sqlalchemy import (BigInteger, Column, Double, ForeignKey, Index, Integer, MetaData, Table, Text,
                        UniqueConstraint, case, create_engine, event, func, inspect, select, text, tuple_,
                        update)
from sqlalchemy import exc as sa_exc
from sqlalchemy.engine import make_url

from motorjig.station.report import operator_name

SCHEMA_VERSION = 2  # 1: the first; 2: runs.slot


def _add_slot(c):
    """1 -> 2: multi-up stations record each run's slot; the runs stored before were not slots."""
    c.execute(text("ALTER TABLE runs ADD COLUMN slot TEXT"))
    c.execute(text("CREATE INDEX runs_slot ON runs (plan, slot, verdict)"))


# {version: function(connection)} turning a database of that version into version + 1, run in
# the opening transaction; a database older than the oldest key here is refused.
MIGRATIONS = {1: _add_slot}

LOCK_RETRIES = 20        # attempts at a write transaction that SQLite reports locked
BUSY_TIMEOUT_S = 30.0    # how long SQLite waits for the write lock before "database is locked"

md = MetaData()
meta_t = Table("meta", md,
               Column("key", Text, primary_key=True),
               Column("value", Text, nullable=False))
runs_t = Table("runs", md,
               Column("id", Integer, primary_key=True, autoincrement=True),
               Column("plan", Text, nullable=False),
               Column("plan_version", Text, nullable=False),
               Column("plan_hash", Text),
               Column("plan_file", Text),
               Column("dut", Text, nullable=False),
               Column("station", Text, nullable=False),
               Column("operator", Text, nullable=False),
               Column("drive_slave", Integer),
               Column("drive_protocol", Integer),
               Column("drive_slave_type", Integer),
               Column("drive_name", Text),
               Column("start_ms", BigInteger, nullable=False),
               Column("end_ms", BigInteger),
               Column("verdict", Text, nullable=False),
               Column("details", Text, nullable=False),
               Column("stored_ms", BigInteger, nullable=False),
               Column("slot", Text),  # the fixture position of a multi-up run, NULL otherwise (version 2)
               # a run's identity: storing the same record again finds it
               UniqueConstraint("plan", "dut", "start_ms", "station", name="runs_identity"),
               Index("runs_yield", "plan", "dut", "start_ms", "verdict"),  # covers the yield query
               Index("runs_start", "start_ms"),
               Index("runs_dut", "dut", "start_ms"),
               Index("runs_slot", "plan", "slot", "verdict"))  # covers the yield per slot
phases_t = Table("phases", md,
                 Column("run_id", Integer, ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True),
                 Column("idx", Integer, primary_key=True),
                 Column("name", Text, nullable=False),
                 Column("outcome", Text, nullable=False),
                 Column("start_ms", BigInteger),
                 Column("end_ms", BigInteger),
                 sqlite_with_rowid=False)
series_t = Table("series", md,
                 Column("id", Integer, primary_key=True, autoincrement=True),
                 Column("plan", Text, nullable=False),
                 Column("phase", Text, nullable=False),
                 Column("name", Text, nullable=False),
                 Column("unit", Text, nullable=False),        # '' without a unit
                 Column("validators", Text, nullable=False),  # '' without limits
                 Column("low", Double),
                 Column("high", Double),
                 UniqueConstraint("plan", "phase", "name", "unit", "validators", name="series_identity"))
measurements_t = Table("measurements", md,
                       Column("run_id", Integer, ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True),
                       Column("seq", Integer, primary_key=True),
                       Column("phase_idx", Integer, nullable=False),
                       Column("series_id", Integer, ForeignKey("series.id"), nullable=False),
                       Column("value_num", Double),
                       Column("value_text", Text),
                       Column("outcome", Text, nullable=False),
                       # covers the capability query: every value of a series, without the table
                       Index("measurements_series", "series_id", "value_num"),
                       sqlite_with_rowid=False)
files_t = Table("run_files", md,
                Column("run_id", Integer, ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True),
                Column("kind", Text, primary_key=True),
                Column("path", Text, nullable=False),
                sqlite_with_rowid=False)
OUR_TABLES = ("runs", "phases", "series", "measurements", "run_files")


class StoreError(Exception):
    """The database cannot be opened, is of another schema version, or refused a query."""


# --- where the database is --------------------------------------------------------------------

def default_path():
    """The default SQLite file: ``$XDG_DATA_HOME/motorjig/results.sqlite`` (``~/.local/share/...``)."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return os.path.join(base, "motorjig", "results.sqlite")


def resolve(db=None):
    """The SQLAlchemy URL for ``db`` (None: the default file; a path; ``sqlite:///...``;
    ``postgresql://...``), checked: StoreError for anything else or a missing driver."""
    if db is None or str(db).strip() == "":
        db = default_path()
    text = os.fspath(db) if not isinstance(db, str) else db
    if "://" not in text:
        path = os.path.abspath(os.path.expanduser(text))
        if os.path.isdir(path):
            raise StoreError("%s is a folder: give the database file, e.g. %s" % (path, os.path.join(path,
                                                                                                  "results.sqlite")))
        return make_url("sqlite:///" + path)
    try:
        url = make_url(text)
    except sa_exc.ArgumentError:
        raise StoreError("%r is neither a file name nor a database URL (sqlite:///FILE, "
                         "postgresql://USER@HOST/DB)" % text) from None
    backend = url.get_backend_name()
    if backend in ("postgres", "postgresql"):
        if url.drivername in ("postgres", "postgresql"):
            url = url.set(drivername="postgresql+psycopg")
        if url.drivername == "postgresql+psycopg":
            try:
                import psycopg  # noqa: F401
            except ImportError:
                raise StoreError("PostgreSQL needs the psycopg driver: pip install 'motorjig[station]'") from None
        if not url.database:
            raise StoreError("%s names no database: postgresql://USER@HOST/DATABASE" % _safe(url))
        return url
    if backend == "sqlite":
        if not url.database or url.database == ":memory:":
            raise StoreError("an in-memory SQLite database keeps nothing: give a file, sqlite:///FILE")
        return url
    raise StoreError("%s: only SQLite (a file) and PostgreSQL (postgresql://...) are supported" % _safe(url))


def _safe(url):
    return url.render_as_string(hide_password=True)


def describe(url):
    """What messages call the database: the file for SQLite, the URL without password otherwise."""
    if url.get_backend_name() == "sqlite":
        return url.database
    return _safe(url).replace("postgresql+psycopg://", "postgresql://")


def open_store(db=None, create=True):
    """Open (creating or upgrading on first use) the results database ``db``; see ``resolve``.
    ``create=False`` (what only reads): a database that does not exist, or holds no MotorJig
    results, is refused instead of created (a mistyped --db says so instead of answering "no runs")."""
    return Store(resolve(db), create=create)


# --- times ---------------------------------------------------------------------------------------

def parse_time(value, end=False):
    """Milliseconds since the epoch of a time bound: None; a ``datetime`` / ``date``; or text:
    ``YYYY-MM-DD``, ``YYYY-MM-DD HH:MM[:SS]`` (local time unless it has an offset), ``today``,
    ``yesterday``, ``7d`` / ``12h`` / ``30m`` (that long ago). With ``end`` the bound is
    exclusive and a date means the end of that day."""
    if value is None:
        return None
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return int(value)
    if isinstance(value, datetime.datetime):
        dt = value if value.tzinfo else value.astimezone()
        return int(dt.timestamp() * 1000) + (1 if end else 0)
    if isinstance(value, datetime.date):
        day = value + datetime.timedelta(days=1) if end else value
        return int(datetime.datetime(day.year, day.month, day.day).astimezone().timestamp() * 1000)
    text = str(value).strip()
    low = text.lower()
    if low in ("today", "yesterday"):
        day = datetime.date.today() - datetime.timedelta(days=1 if low == "yesterday" else 0)
        return parse_time(day, end)
    m = re.fullmatch(r"(\d+)\s*([dhm])", low)
    if m:
        secs = int(m.group(1)) * {"d": 86400, "h": 3600, "m": 60}[m.group(2)]
        return int((time.time() - secs) * 1000)
    try:
        if re.fullmatch(r"\d{4}-\d{2}-\d{2}", text):
            return parse_time(datetime.date.fromisoformat(text), end)
        return parse_time(datetime.datetime.fromisoformat(text.replace("Z", "+00:00")), end)
    except ValueError:
        raise StoreError("%r is not a time: give YYYY-MM-DD, 'YYYY-MM-DD HH:MM', today, yesterday or "
                         "e.g. 7d" % text) from None


def iso(ms):
    """ISO 8601 in UTC of a ms stamp (None stays None)."""
    if ms is None:
        return None
    return datetime.datetime.fromtimestamp(ms / 1000.0, datetime.timezone.utc).isoformat(timespec="milliseconds")


# --- reading a record ------------------------------------------------------------------------


def _limit(text):
    try:
        v = float(text)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


@functools.lru_cache(maxsize=4096)
def _limits_cached(validators):
    return parse_limits(validators)


def parse_limits(validators):
    """(low, high) from OpenHTF validator strings: ``"0.85 <= x <= 1.15"``, ``"x <= 20"``,
    ``"5 <= x"``, ``"x == 100"`` (``x == True``: 1), marginal bounds skipped
    (``"0 <= Marginal:1 <= x <= 10"``), ``"'x' is within 5% of 10."``; several
    validators: the tightest. None where a side has no limit (regexes, equal-to text)."""
    low = high = None
    for v in validators or ():
        v = str(v).strip()
        lo = hi = None
        m = re.fullmatch(r"x\s*==\s*(\S+)", v)
        if m:
            word = m.group(1)
            lo = hi = {"True": 1.0, "False": 0.0}.get(word, _limit(word))
        elif re.search(r"(^|<=)\s*x\s*(<=|$)", v):
            parts = [p.strip() for p in v.split("<=")]
            i = parts.index("x")
            left = [p for p in parts[:i] if not p.startswith("Marginal:")]
            right = [p for p in parts[i + 1:] if not p.startswith("Marginal:")]
            lo = _limit(left[-1]) if left else None
            hi = _limit(right[0]) if right else None
        else:
            m = re.fullmatch(r"'x' is within (\S+)% of (\S+?)\.?(\s.*)?", v)
            if m:
                pct, exp = _limit(m.group(1)), _limit(m.group(2))
                if pct is not None and exp is not None:
                    d = abs(exp) * pct / 100.0
                    lo, hi = exp - d, exp + d
        if lo is not None:
            low = lo if low is None else max(low, lo)
        if hi is not None:
            high = hi if high is None else min(high, hi)
    return low, high


def _value(v):
    """(number or None, text) of a measured value."""
    if isinstance(v, bool):
        return (1.0 if v else 0.0), str(v)
    if isinstance(v, (int, float)):
        try:
            num = float(v)
        except OverflowError:
            num = None
        return (num if num is not None and math.isfinite(num) else None), str(v)
    if isinstance(v, (list, dict)):
        return None, json.dumps(v, separators=(",", ":"))
    return None, None if v is None else str(v)


def _record_kind(drive):
    """The drive kind a record's ``drive`` metadata is of: its ``protocol`` names the kind; a number
    there is the variant of a drive of the default kind (records from before named kinds)."""
    from motorjig.station import kinds

    protocol = drive.get("protocol")
    return kinds.get(protocol if isinstance(protocol, str) and protocol in kinds.names() else kinds.DEFAULT)


def _int(v):
    try:
        return int(v)
    except (TypeError, ValueError):
        return None


def _slot(v):
    """The slot a record names (``metadata["slot"]``) as text; None for a run that was not a slot."""
    if v is None or isinstance(v, bool):
        return None
    v = str(v).strip()
    return v or None


def slot_key(slot):
    """Sort key of slot names: numbers by value ("2" before "10"), "A3" before "A10", no slot last."""
    if slot is None:
        return (1, ())
    return (0, tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in re.findall(r"\d+|\D+", slot)))


def _ms(v):
    try:
        return int(v)
    except (TypeError, ValueError):
        return None


def _flatten(record, files):
    """The rows of one record: (run, phases, [(series key, limits, measurement row)], files)."""
    if not isinstance(record, dict):
        from motorjig.station.report import record_dict  # an OpenHTF TestRecord

        record = record_dict(record)
    md_ = record.get("metadata") or {}
    drive = md_.get("drive") or {}
    kind = _record_kind(drive)  # the drive_protocol number and the identity text are its kind's
    start = _ms(record.get("start_time_millis"))
    if start is None:
        raise StoreError("the record has no start time (start_time_millis): not a test record")
    details = "; ".join(str(d.get("description") or d.get("code") or "")
                        for d in record.get("outcome_details") or () if isinstance(d, dict))
    run = {"plan": str(md_.get("test_name") or record.get("test_name") or "unknown"),
           "plan_version": str(md_.get("test_version") or ""),
           "plan_hash": md_.get("plan_hash") or None, "plan_file": md_.get("plan_file") or None,
           "dut": str(record.get("dut_id") or "unknown"), "station": str(record.get("station_id") or ""),
           "operator": operator_name(md_.get("operator")),
           "drive_slave": _int(drive.get("slave", drive.get("node_id"))), "drive_protocol": kind.record_code(drive),
           "drive_slave_type": _int(drive.get("slave_type", drive.get("device_type"))),
           "drive_name": drive.get("name") or kind.identity_text(drive),
           "start_ms": start, "end_ms": _ms(record.get("end_time_millis")),
           "verdict": str(record.get("outcome") or "ERROR").upper(), "details": details,
           "stored_ms": int(time.time() * 1000), "slot": _slot(md_.get("slot"))}
    phases, meas = [], []
    for idx, ph in enumerate(record.get("phases") or ()):
        phases.append({"idx": idx, "name": str(ph.get("name") or "phase%d" % idx),
                       "outcome": str(ph.get("outcome") or ""), "start_ms": _ms(ph.get("start_time_millis")),
                       "end_ms": _ms(ph.get("end_time_millis"))})
        for name, m in (ph.get("measurements") or {}).items():
            validators = [str(v) for v in m.get("validators") or ()]
            units = m.get("units") or {}
            unit = str(units.get("suffix") or units.get("name") or "") if isinstance(units, dict) else str(units)
            key = (run["plan"], phases[-1]["name"], str(m.get("name") or name), unit, " and ".join(validators))
            num, text = _value(m["measured_value"]) if "measured_value" in m else (None, None)
            meas.append((key, _limits_cached(tuple(validators)),
                         {"seq": len(meas), "phase_idx": idx, "value_num": num, "value_text": text,
                          "outcome": str(m.get("outcome") or ("UNSET" if "measured_value" not in m else ""))}))
    file_rows = [{"kind": str(k), "path": os.path.abspath(str(p))} for k, p in (files or {}).items() if p]
    return run, phases, meas, file_rows


# --- the store -----------------------------------------------------------------------------------

class Store:
    """One results database (open with ``open_store``); safe to share between threads."""

    def __init__(self, url, create=True):
        self.url = url
        self.name = describe(url)
        self.dialect = url.get_backend_name()
        self._series = {}  # series key -> id, only ids of committed rows
        self._create = create
        if self.dialect == "sqlite":
            if not create and not os.path.exists(url.database):
                raise StoreError("there is no results database %s (check --db or $JIGCTL_DB; jigctl test "
                                 "creates one with its first run)" % self.name)
            folder = os.path.dirname(os.path.abspath(url.database))
            try:
                os.makedirs(folder, exist_ok=True)
            except OSError as exc:
                raise StoreError("cannot create the folder of %s: %s" % (self.name, exc.strerror or exc)) from None
            self.engine = create_engine(url, connect_args={"timeout": BUSY_TIMEOUT_S, "check_same_thread": False})
            event.listen(self.engine, "connect", _sqlite_connect)
            event.listen(self.engine, "begin", _sqlite_begin)
        else:
            self.engine = create_engine(url, pool_pre_ping=True)
        try:
            self._prepare()
        except BaseException:
            self.engine.dispose()
            raise

    def close(self):
        self.engine.dispose()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self):
        return "<Store %s>" % self.name

    # --- transactions --------------------------------------------------------------------------
    def _error(self, exc):
        orig = getattr(exc, "orig", None) or exc
        text = str(orig).strip().splitlines()[0] if str(orig).strip() else type(orig).__name__
        if isinstance(exc, sa_exc.OperationalError) and self.dialect == "postgresql":
            return StoreError("cannot use the database %s: %s" % (self.name, text))
        if "file is not a database" in text:
            return StoreError("%s is not a SQLite database" % self.name)
        if "unable to open database file" in text:
            return StoreError("cannot open %s (check the folder and its permissions)" % self.name)
        return StoreError("database error in %s: %s" % (self.name, text))

    def _read(self, fn):
        try:
            with self.engine.connect() as c:
                return fn(c)
        except sa_exc.SQLAlchemyError as exc:
            raise self._error(exc) from None

    def _write(self, fn):
        """Run ``fn(connection, pending)`` in one write transaction, again while SQLite says
        locked or a concurrent writer inserted the same row first; ``pending`` collects
        series ids that become valid once this transaction has committed."""
        for attempt in range(LOCK_RETRIES):
            pending = {}
            try:
                with self.engine.connect() as c:
                    c.execution_options(motorjig_write=True)
                    with c.begin():
                        result = fn(c, pending)
                self._series.update(pending)
                return result
            except sa_exc.IntegrityError as exc:
                if attempt >= 3:
                    raise self._error(exc) from None
            except sa_exc.OperationalError as exc:
                text = str(getattr(exc, "orig", exc)).lower()
                if not ("locked" in text or "busy" in text) or attempt == LOCK_RETRIES - 1:
                    raise self._error(exc) from None
                time.sleep(random.uniform(0.01, 0.05) * (1 + attempt))
            except sa_exc.SQLAlchemyError as exc:
                raise self._error(exc) from None
        raise StoreError("%s stayed locked: another program holds it" % self.name)

    # --- schema ----------------------------------------------------------------------------------
    def _version(self, c):
        """The schema version, None for a database without our tables; refuses foreign ones."""
        names = set(inspect(c).get_table_names())
        if "meta" not in names:
            ours = names.intersection(OUR_TABLES)
            if ours:
                raise StoreError("%s has tables %s but no 'meta' table with a schema version: not a MotorJig "
                                 "results database" % (self.name, ", ".join(sorted(ours))))
            return None
        value = c.execute(select(meta_t.c.value).where(meta_t.c.key == "schema_version")).scalar()
        try:
            return int(value)
        except (TypeError, ValueError):
            raise StoreError("%s has a 'meta' table without a schema version: not a MotorJig results "
                             "database" % self.name) from None

    def _check(self, version):
        if version is not None and version > SCHEMA_VERSION:
            raise StoreError("%s has schema version %d, newer than this motorjig knows (%d): update motorjig "
                             "(it was written by a newer one and is left as it is)"
                             % (self.name, version, SCHEMA_VERSION))
        if version is not None and version < SCHEMA_VERSION and version not in MIGRATIONS:
            raise StoreError("%s has schema version %d, older than this motorjig can upgrade (%d): it is left "
                             "as it is; use the motorjig that wrote it, or a new database"
                             % (self.name, version, SCHEMA_VERSION))

    def _prepare(self):
        version = self._read(self._version)
        self._check(version)
        if version == SCHEMA_VERSION:
            return
        if version is None and not self._create:
            raise StoreError("%s holds no MotorJig results (check --db or $JIGCTL_DB; jigctl test creates the "
                             "tables with its first run)" % self.name)

        def create_or_upgrade(c, pending):
            v = self._version(c)  # again, under the write lock: another station may have done it
            self._check(v)
            if v is None:
                md.create_all(c)
                c.execute(meta_t.insert(), [{"key": "schema_version", "value": str(SCHEMA_VERSION)},
                                            {"key": "created_ms", "value": str(int(time.time() * 1000))}])
                return
            while v < SCHEMA_VERSION:
                if v not in MIGRATIONS:
                    self._check(v)
                try:
                    MIGRATIONS[v](c)
                except Exception as exc:
                    raise StoreError("upgrading %s from schema version %d to %d failed (%s): it is left at "
                                     "version %d" % (self.name, v, v + 1, exc, v)) from exc
                v += 1
                c.execute(update(meta_t).where(meta_t.c.key == "schema_version").values(value=str(v)))

        try:
            self._write(create_or_upgrade)
        except StoreError:
            # two stations creating the schema at once: the loser's CREATE fails, the winner's stands
            if self._read(self._version) != SCHEMA_VERSION:
                raise

    def schema_version(self):
        return self._read(self._version)

    # --- storing ---------------------------------------------------------------------------------
    def _insert_ignore(self):
        if self.dialect == "postgresql":
            from sqlalchemy.dialects.postgresql import insert
        else:
            from sqlalchemy.dialects.sqlite import insert
        return insert(series_t).on_conflict_do_nothing(
            index_elements=["plan", "phase", "name", "unit", "validators"])

    def _series_ids(self, c, pending, plan, wanted):
        """Ids of the series keys ``wanted`` ({key: (low, high)}), inserting new ones."""
        ids = {k: self._series[k] for k in wanted if k in self._series}
        missing = [k for k in wanted if k not in ids]
        if not missing:
            return ids

        def load():
            cols = (series_t.c.id, series_t.c.plan, series_t.c.phase, series_t.c.name, series_t.c.unit,
                    series_t.c.validators)
            return {tuple(r[1:]): r[0] for r in c.execute(select(*cols).where(series_t.c.plan == plan))}

        known = load()
        new = [k for k in missing if k not in known]
        if new:
            c.execute(self._insert_ignore(), [
                {"plan": k[0], "phase": k[1], "name": k[2], "unit": k[3], "validators": k[4],
                 "low": wanted[k][0], "high": wanted[k][1]} for k in new])
            known = load()
        pending.update(known)
        ids.update((k, known[k]) for k in missing)
        return ids

    def _insert_run(self, c, pending, run, phases, meas, file_rows):
        ident = (runs_t.c.plan == run["plan"]) & (runs_t.c.dut == run["dut"]) & \
                (runs_t.c.start_ms == run["start_ms"]) & (runs_t.c.station == run["station"])
        existing = c.execute(select(runs_t.c.id).where(ident)).scalar()
        if existing is not None:
            return existing
        run_id = c.execute(runs_t.insert().values(**run)).inserted_primary_key[0]
        wanted = {}
        for key, limits, _ in meas:
            wanted.setdefault(key, limits)
        ids = self._series_ids(c, pending, run["plan"], wanted)
        if phases:
            c.execute(phases_t.insert(), [dict(p, run_id=run_id) for p in phases])
        if meas:
            c.execute(measurements_t.insert(), [dict(row, run_id=run_id, series_id=ids[key])
                                                for key, _, row in meas])
        if file_rows:
            c.execute(files_t.insert(), [dict(f, run_id=run_id) for f in file_rows])
        return run_id

    def add_run(self, record, files=None):
        """Store one run (an OpenHTF record as dict, or a TestRecord) in one transaction; its id.
        ``files``: {kind: path}, e.g. the runner's {"json": ..., "xml": ..., "html": ...}."""
        rows = _flatten(record, files)
        return self._write(lambda c, pending: self._insert_run(c, pending, *rows))

    def add_runs(self, records):
        """Store many runs in one transaction with bulk inserts (imports, benchmarks); their ids in
        order (a run stored already keeps its id). ``records``: records, or (record, files) pairs."""
        flat = [_flatten(*(r if isinstance(r, tuple) else (r, None))) for r in records]
        key = lambda run: (run["plan"], run["dut"], run["start_ms"], run["station"])  # noqa: E731

        def insert_all(c, pending):
            ids, first = {}, {}
            for i, rows in enumerate(flat):
                first.setdefault(key(rows[0]), i)  # the same record twice in the batch: stored once
            r = runs_t.c
            for lo in range(0, len(first), 500):
                chunk = list(first)[lo:lo + 500]
                q = select(r.id, r.plan, r.dut, r.start_ms, r.station).where(
                    tuple_(r.plan, r.dut, r.start_ms, r.station).in_(chunk))
                ids.update((tuple(row[1:]), row[0]) for row in c.execute(q))
            new = [i for k, i in first.items() if k not in ids]
            if new:
                got = c.execute(runs_t.insert().returning(r.id, sort_by_parameter_order=True),
                                [flat[i][0] for i in new]).scalars().all()
                ids.update((key(flat[i][0]), run_id) for i, run_id in zip(new, got))
            series_ids = {}
            by_plan = {}
            for i in new:
                for skey, limits, _ in flat[i][2]:
                    by_plan.setdefault(skey[0], {}).setdefault(skey, limits)
            for plan, wanted in by_plan.items():
                series_ids.update(self._series_ids(c, pending, plan, wanted))
            phase_rows, meas_rows, file_rows = [], [], []
            for i in new:
                run, phases, meas, files = flat[i]
                run_id = ids[key(run)]
                phase_rows += [dict(p, run_id=run_id) for p in phases]
                meas_rows += [dict(row, run_id=run_id, series_id=series_ids[skey]) for skey, _, row in meas]
                file_rows += [dict(f, run_id=run_id) for f in files]
            for table, rows in ((phases_t, phase_rows), (measurements_t, meas_rows), (files_t, file_rows)):
                if rows:
                    c.execute(table.insert(), rows)
            return [ids[key(rows[0])] for rows in flat]

        return self._write(insert_all)

    # --- queries ---------------------------------------------------------------------------------
    @staticmethod
    def _run_dict(r):
        return {"id": r.id, "plan": r.plan, "plan_version": r.plan_version, "plan_hash": r.plan_hash,
                "dut": r.dut, "station": r.station, "slot": r.slot, "operator": operator_name(r.operator),
                "verdict": r.verdict, "start_ms": r.start_ms, "end_ms": r.end_ms, "start": iso(r.start_ms),
                "end": iso(r.end_ms), "seconds": None if r.end_ms is None else (r.end_ms - r.start_ms) / 1000.0,
                "details": r.details}

    @staticmethod
    def _filters(dut=None, plan=None, verdict=None, since=None, until=None, station=None, slot=None):
        where = []
        if station is not None:
            where.append(runs_t.c.station == str(station))
        if slot is not None:
            where.append(runs_t.c.slot == str(slot))
        if dut is not None:
            where.append(runs_t.c.dut == str(dut))
        if plan is not None:
            where.append(runs_t.c.plan == str(plan))
        if verdict is not None:
            where.append(runs_t.c.verdict == str(verdict).upper())
        lo, hi = parse_time(since), parse_time(until, end=True)
        if lo is not None:
            where.append(runs_t.c.start_ms >= lo)
        if hi is not None:
            where.append(runs_t.c.start_ms < hi)
        return where

    def runs(self, dut=None, plan=None, verdict=None, since=None, until=None, limit=50, station=None, slot=None):
        """The last runs, newest first (``limit`` None or 0: all), as dicts; ``station``, ``slot``:
        of that station, that slot only."""
        q = select(runs_t).where(*self._filters(dut, plan, verdict, since, until, station, slot)) \
            .order_by(runs_t.c.start_ms.desc(), runs_t.c.id.desc())
        if limit:
            q = q.limit(int(limit))
        return self._read(lambda c: [self._run_dict(r) for r in c.execute(q)])

    def run(self, run_id):
        """One run with its drive, files, phases and every measurement; None if there is none."""
        def query(c):
            r = c.execute(select(runs_t).where(runs_t.c.id == int(run_id))).first()
            if r is None:
                return None
            out = self._run_dict(r)
            out.update(plan_file=r.plan_file, stored=iso(r.stored_ms),
                       drive={"slave": r.drive_slave, "protocol": r.drive_protocol,
                              "slave_type": r.drive_slave_type, "name": r.drive_name})
            out["files"] = {f.kind: f.path for f in c.execute(
                select(files_t).where(files_t.c.run_id == r.id).order_by(files_t.c.kind))}
            phases = [{"name": p.name, "outcome": p.outcome, "start_ms": p.start_ms, "end_ms": p.end_ms,
                       "measurements": []}
                      for p in c.execute(select(phases_t).where(phases_t.c.run_id == r.id).order_by(phases_t.c.idx))]
            m, s = measurements_t, series_t
            for row in c.execute(select(m.c.phase_idx, s.c.name, m.c.value_num, m.c.value_text, s.c.unit, s.c.low,
                                        s.c.high, s.c.validators, m.c.outcome)
                                 .join(s, s.c.id == m.c.series_id).where(m.c.run_id == r.id).order_by(m.c.seq)):
                phases[row.phase_idx]["measurements"].append(
                    {"name": row.name, "value": row.value_num, "text": row.value_text, "unit": row.unit or None,
                     "low": row.low, "high": row.high, "limits": row.validators or None, "outcome": row.outcome})
            out["phases"] = phases
            return out

        return self._read(query)

    def plans(self):
        """{plan name: number of runs}."""
        q = select(runs_t.c.plan, func.count()).group_by(runs_t.c.plan).order_by(runs_t.c.plan)
        return self._read(lambda c: {p: n for p, n in c.execute(q)})

    def slots(self, plan=None):
        """{slot name: number of runs} of the runs that were slots (of ``plan``), in slot order."""
        q = select(runs_t.c.slot, func.count()).where(runs_t.c.slot.isnot(None), *self._filters(plan=plan)) \
            .group_by(runs_t.c.slot)
        return self._read(lambda c: dict(sorted(c.execute(q).all(), key=lambda row: slot_key(row[0]))))

    def yield_(self, plan, slot=None):
        """First-pass yield (a DUT's first run passed) and final yield (its last run passed),
        over every DUT that has a run of the plan; fractions, None without runs. A DUT's runs are
        ordered by their start time. ``slot``: over the runs of that slot only (the answer says it)."""
        r = runs_t.c
        failed = case((r.verdict == "PASS", 0), else_=1)
        # one pass over the covering index runs_yield: the first run's start time and verdict
        # packed into one number (2 * start + failed), its minimum per DUT; the last's likewise
        per_dut = select(func.min(r.start_ms * 2 + failed).label("first"),
                         func.max(r.start_ms * 2 + 1 - failed).label("last"),
                         func.count().label("n")).where(*self._filters(plan=plan, slot=slot)) \
            .group_by(r.dut).subquery()
        q = select(func.count(), func.coalesce(func.sum(per_dut.c.n), 0),
                   func.coalesce(func.sum(case((per_dut.c.first % 2 == 0, 1), else_=0)), 0),
                   func.coalesce(func.sum(case((per_dut.c.last % 2 == 1, 1), else_=0)), 0))
        duts, n_runs, first, last = self._read(lambda c: c.execute(q).one())
        out = {"plan": str(plan), "runs": int(n_runs), "duts": int(duts), "first_pass": int(first),
               "final_pass": int(last), "first_pass_yield": first / duts if duts else None,
               "final_yield": last / duts if duts else None}
        if slot is not None:
            out["slot"] = str(slot)
        return out

    def yield_by_slot(self, plan, slot=None):
        """Per slot of ``plan`` (``slot``: that one only), in slot order, runs without a slot last
        (slot None): runs, pass, fail, error (every other verdict: ERROR, TIMEOUT, ABORTED) and
        yield = pass / runs. Runs, not DUTs: a DUT retested goes to whichever slot is free, and
        what a slot's own fault costs is the share of its runs that did not pass."""
        r = runs_t.c
        count = lambda verdict: func.coalesce(func.sum(case((r.verdict == verdict, 1), else_=0)), 0)  # noqa: E731
        q = select(r.slot, func.count(), count("PASS"), count("FAIL")) \
            .where(*self._filters(plan=plan, slot=slot)).group_by(r.slot)
        rows = sorted(self._read(lambda c: c.execute(q).all()), key=lambda row: slot_key(row[0]))
        return [{"slot": s, "runs": int(n), "pass": int(p), "fail": int(f), "error": int(n - p - f),
                 "yield": p / n} for s, n, p, f in rows]

    @staticmethod
    def _spread(c, n, total, squares, lo, hi, deviations):
        """(mean, sigma) of n values from their sum and sum of squares; ``deviations(mean)``: the
        sum of squared deviations from the mean, a second pass when one pass keeps too few digits."""
        mean = total / n
        if n < 2:
            return mean, None
        if lo == hi:
            return mean, 0.0
        var = (squares - total * total / n) / (n - 1)
        # one pass keeps too few digits of a spread this small against the mean
        # (sigma under 0.3 % of it): a second pass over the deviations from the mean
        if var <= 0 or mean * mean > 1e5 * var:
            var = c.execute(deviations(mean)).scalar() / (n - 1)
        return mean, math.sqrt(max(var, 0.0))

    @staticmethod
    def _stat(series, n, mean, sigma, lo, hi):
        return {"step": series.phase, "measurement": series.name, "unit": series.unit or None, "n": int(n),
                "min": lo, "mean": mean, "max": hi, "sigma": sigma, "low": series.low, "high": series.high,
                "limits": series.validators or None, "cpk": cpk(mean, sigma, series.low, series.high)}

    def stats(self, plan, slot=None):
        """Per step + measurement of ``plan`` with numeric values: n, min, mean, max, sigma
        (sample standard deviation), the limits and Cpk = min(USL - mean, mean - LSL) / (3 sigma)
        (one-sided with one limit; None when sigma is 0 or unknown, or without limits). A
        measurement whose limits or unit changed between plan versions has one entry per set.
        ``slot``: over the runs of that slot only (``stats_by_slot``)."""
        if slot is not None:
            return [{k: v for k, v in row.items() if k != "slot"} for row in self.stats_by_slot(plan, slot)]
        m, s = measurements_t, series_t
        v = m.c.value_num
        # min and max: two seeks per series in the index measurements_series; n, sum and sum of
        # squares: one pass over that index for all the plan's series (PostgreSQL scans it in parallel)
        ends = select(s, select(func.min(v)).where(m.c.series_id == s.c.id).scalar_subquery().label("lo"),
                      select(func.max(v)).where(m.c.series_id == s.c.id).scalar_subquery().label("hi")) \
            .where(s.c.plan == str(plan)).order_by(s.c.id)

        def query(c):
            series = [r for r in c.execute(ends).all() if r.lo is not None]  # the others: text, unset
            if not series:
                return []
            agg = {row[0]: row[1:] for row in c.execute(
                select(m.c.series_id, func.count(v), func.sum(v), func.sum(v * v))
                .where(m.c.series_id.in_([r.id for r in series])).group_by(m.c.series_id))}
            out = []
            for r in series:
                n, total, squares = agg[r.id]
                mean, sigma = self._spread(
                    c, n, total, squares, r.lo, r.hi,
                    lambda mean, r=r: select(func.sum((v - mean) * (v - mean))).where(m.c.series_id == r.id,
                                                                                      v.isnot(None)))
                out.append(self._stat(r, n, mean, sigma, r.lo, r.hi))
            return out

        return self._read(query)

    def stats_by_slot(self, plan, slot=None):
        """``stats`` of ``plan`` per slot (``slot``: that one only): the same entries, each with its
        ``slot`` (None: the runs that were no slot), by measurement and then in slot order."""
        m, s, r = measurements_t, series_t, runs_t
        v = m.c.value_num
        values_runs = m.join(r, r.c.id == m.c.run_id)
        same_slot = lambda name: r.c.slot.is_(None) if name is None else r.c.slot == name  # noqa: E731

        def query(c):
            series = {row.id: row for row in c.execute(select(s).where(s.c.plan == str(plan)))}
            if not series:
                return []
            # one pass over the plan's values joined to their runs: n, sum, squares, min, max a slot
            agg = c.execute(select(m.c.series_id, r.c.slot, func.count(v), func.sum(v), func.sum(v * v),
                                   func.min(v), func.max(v)).select_from(values_runs)
                            .where(m.c.series_id.in_(list(series)), v.isnot(None),
                                   *self._filters(plan=plan, slot=slot))
                            .group_by(m.c.series_id, r.c.slot)).all()
            out = []
            for sid, name, n, total, squares, lo, hi in sorted(agg, key=lambda a: (a[0], slot_key(a[1]))):
                mean, sigma = self._spread(
                    c, n, total, squares, lo, hi,
                    lambda mean, sid=sid, name=name: select(func.sum((v - mean) * (v - mean)))
                    .select_from(values_runs).where(m.c.series_id == sid, v.isnot(None), same_slot(name)))
                out.append(dict(self._stat(series[sid], n, mean, sigma, lo, hi), slot=name))
            return out

        return self._read(query)

    def export_csv(self, dest, dut=None, plan=None, verdict=None, since=None, until=None, slot=None):
        """Every measurement of the runs that match, one CSV row each, oldest run first, to
        ``dest`` (a path, or a text file object); the number of rows. A run without measurements
        (refused at the preflight, an error before its first step) is one row with empty step,
        measurement and value, so that yield computed from the file counts it as the database does.
        The run's slot is the last column (after the columns of version 1: scripts that read those
        by position keep working), empty for a run that was not a slot."""
        m, s, r = measurements_t, series_t, runs_t
        q = select(r.c.id, r.c.start_ms, r.c.plan, r.c.plan_version, r.c.plan_hash, r.c.dut, r.c.station,
                   r.c.operator, r.c.verdict, s.c.phase, s.c.name, m.c.value_text, m.c.value_num, s.c.unit, s.c.low,
                   s.c.high, s.c.validators, m.c.outcome, r.c.slot) \
            .select_from(r.outerjoin(m, m.c.run_id == r.c.id).outerjoin(s, s.c.id == m.c.series_id)) \
            .where(*self._filters(dut, plan, verdict, since, until, slot=slot)) \
            .order_by(r.c.start_ms, r.c.id, m.c.seq)
        header = ["run_id", "start", "plan", "plan_version", "plan_hash", "dut", "station", "operator", "verdict",
                  "step", "measurement", "value", "number", "unit", "low", "high", "limits", "outcome", "slot"]
        num = lambda x: "" if x is None else repr(x)  # noqa: E731 - shortest exact text of a float

        def write(f):
            w = csv.writer(f, lineterminator="\n")
            w.writerow(header)
            count = 0

            def query(c):
                nonlocal count
                for row in c.execution_options(stream_results=True, yield_per=2000).execute(q):
                    w.writerow([row[0], iso(row[1]), *row[2:7], operator_name(row[7]), *row[8:11],
                                "" if row[11] is None else row[11], num(row[12]), row[13], num(row[14]),
                                num(row[15]), row[16], row[17], row[18] or ""])
                    count += 1

            self._read(query)
            return count

        if isinstance(dest, io.IOBase) or hasattr(dest, "write"):
            return write(dest)
        tmp = "%s.part" % dest
        try:
            with open(tmp, "w", encoding="utf-8", newline="") as f:
                n = write(f)
            os.replace(tmp, dest)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
        return n


def cpk(mean, sigma, low, high):
    """Process capability index against the limits; None without a spread or without limits."""
    if not sigma or (low is None and high is None):
        return None
    sides = []
    if high is not None:
        sides.append((high - mean) / (3 * sigma))
    if low is not None:
        sides.append((mean - low) / (3 * sigma))
    return min(sides)


# --- SQLite connection set-up --------------------------------------------------------------------

def _sqlite_connect(dbapi_conn, _record):
    # SQLAlchemy emits BEGIN itself (_sqlite_begin): the sqlite3 module's own transaction
    # handling would start write transactions deferred, which fail at once when two writers meet.
    dbapi_conn.isolation_level = None
    cur = dbapi_conn.cursor()
    try:
        cur.execute("PRAGMA busy_timeout = %d" % int(BUSY_TIMEOUT_S * 1000))
        cur.execute("PRAGMA journal_mode = WAL")  # readers never block the writer, the writer not them
        cur.execute("PRAGMA foreign_keys = ON")
    finally:
        cur.close()


def _sqlite_begin(conn):
    write = conn.get_execution_options().get("motorjig_write", False)
    conn.exec_driver_sql("BEGIN IMMEDIATE" if write else "BEGIN")


__all__ = ["SCHEMA_VERSION", "MIGRATIONS", "Store", "StoreError", "open_store", "default_path", "resolve",
           "parse_limits", "parse_time", "cpk", "iso", "operator_name", "slot_key"]
