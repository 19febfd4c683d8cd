"""A throw-away PostgreSQL server for tests and benchmarks: ``initdb`` + ``pg_ctl`` in a temporary folder.

    with TempCluster() as pg:                  # a cluster on a free port of 127.0.0.1
        url = pg.create_database("results")    # postgresql://motorjig@127.0.0.1:PORT/results

The server binaries are found on $PATH or in Debian's ``/usr/lib/postgresql/<major>/bin``
(``find_bin``; None when there are none: callers skip). The cluster trusts every local
connection (user ``motorjig``), listens on 127.0.0.1 only plus a unix socket in its own
folder, and is stopped and deleted on ``stop()`` / leaving the ``with`` (and at exit).
PostgreSQL refuses to run as root, so as root the server runs as the ``postgres`` user
that Debian's package creates (``runuser``), its folder handed to that user.
"""

import atexit
import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile

USER = "motorjig"


class ClusterError(Exception):
    """The server could not be set up or started (the message has its log's last lines)."""


def find_bin():
    """The folder of initdb / pg_ctl / postgres, or None."""
    found = shutil.which("initdb")
    if found:
        d = os.path.dirname(os.path.realpath(found))  # /usr/local/bin/initdb may be a link into the real folder
        if all(os.path.exists(os.path.join(d, n)) for n in ("pg_ctl", "postgres", "createdb")):
            return d
    cands = [d for d in glob.glob("/usr/lib/postgresql/*/bin")
             if all(os.path.exists(os.path.join(d, n)) for n in ("initdb", "pg_ctl", "postgres", "createdb"))]
    if not cands:
        return None

    def major(d):
        try:
            return float(d.split("/")[-2])
        except ValueError:
            return 0.0

    return max(cands, key=major)


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class TempCluster:
    """One temporary PostgreSQL cluster. ``fast=True`` (tests) turns fsync and synchronous
    commit off; ``fast=False`` (the benchmark) keeps the server's durable defaults."""

    def __init__(self, fast=True, settings=None):
        self.fast = fast
        self.settings = dict(settings or {})
        self.bindir = find_bin()
        self.dir = None
        self.port = None
        self._run_as = None
        self._started = False

    # --- running the binaries --------------------------------------------------------
    def _cmd(self, name, *args):
        cmd = [os.path.join(self.bindir, name), *args]
        if self._run_as:
            cmd = ["runuser", "-u", self._run_as, "--", *cmd]
        return cmd

    def _run(self, name, *args, timeout=60):
        p = subprocess.run(self._cmd(name, *args), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True, timeout=timeout, cwd=self.dir)
        if p.returncode != 0:
            raise ClusterError("%s failed (exit %d): %s" % (name, p.returncode, p.stdout.strip()[-800:]))
        return p.stdout

    def _pick_user(self):
        if os.geteuid() != 0:
            return None, None
        for name in ("postgres", "nobody"):
            try:
                pw = pwd.getpwnam(name)
            except KeyError:
                continue
            return name, pw
        raise ClusterError("running as root and there is no 'postgres' user to run the server as")

    # --- life cycle ------------------------------------------------------------------
    def start(self):
        if self.bindir is None:
            raise ClusterError("PostgreSQL server binaries (initdb, pg_ctl) not found")
        self._run_as, pw = self._pick_user()
        self.dir = tempfile.mkdtemp(prefix="mjpg-")
        if pw is not None:
            os.chown(self.dir, pw.pw_uid, pw.pw_gid)
        data = os.path.join(self.dir, "data")
        self._run("initdb", "-D", data, "-U", USER, "--auth=trust", "-E", "UTF8", "--locale=C", "--no-sync",
                  timeout=120)
        opts = {"listen_addresses": "127.0.0.1", "unix_socket_directories": self.dir, "max_connections": "40"}
        if self.fast:
            opts.update(fsync="off", synchronous_commit="off", full_page_writes="off")
        opts.update(self.settings)
        atexit.register(self.stop)
        for attempt in range(5):  # a free port can be taken between the probe and the start
            self.port = free_port()
            o = " ".join("-c %s=%s" % kv for kv in dict(opts, port=str(self.port)).items())
            try:
                self._run("pg_ctl", "start", "-w", "-t", "60", "-D", data, "-l", os.path.join(self.dir, "log"),
                          "-o", o, timeout=90)
                self._started = True
                return self
            except ClusterError:
                if attempt == 4:
                    raise ClusterError("the PostgreSQL server did not start: %s" % self.log_tail()) from None
        return self

    def log_tail(self, n=15):
        try:
            with open(os.path.join(self.dir, "log"), encoding="utf-8", errors="replace") as f:
                return " | ".join(f.read().splitlines()[-n:])
        except OSError:
            return "(no log)"

    def stop(self):
        if self.dir is None:
            return
        if self._started:
            try:
                self._run("pg_ctl", "stop", "-w", "-m", "immediate", "-D", os.path.join(self.dir, "data"))
            except (ClusterError, subprocess.TimeoutExpired):
                pass
            self._started = False
        shutil.rmtree(self.dir, ignore_errors=True)
        self.dir = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # --- databases -------------------------------------------------------------------
    def url(self, database="postgres"):
        return "postgresql://%s@127.0.0.1:%d/%s" % (USER, self.port, database)

    def create_database(self, name):
        """A new empty database; its URL."""
        subprocess.run([os.path.join(self.bindir, "createdb"), "-h", "127.0.0.1", "-p", str(self.port), "-U",
                        USER, name], check=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=60)
        return self.url(name)

    def server_version(self):
        """The server's version, e.g. '15.18'."""
        out = subprocess.run([os.path.join(self.bindir, "postgres"), "--version"], stdout=subprocess.PIPE, text=True,
                             timeout=30).stdout
        parts = out.split()
        return parts[2] if len(parts) > 2 else out.strip()
