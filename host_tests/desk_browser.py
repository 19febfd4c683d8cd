"""Helpers for driving MotorJig Desk in Debian's headless Chromium (tests and screenshots).

Selenium is pointed at /usr/bin/chromedriver and /usr/bin/chromium explicitly, so
selenium-manager never runs and nothing is downloaded. The bench and the Desk run
as child processes on free ports bound to 127.0.0.1, so a test can kill the bench
mid-session like an unplugged cable. The browser allows pop-ups (as an operator
does for the Desk, so a run's report opens in a new tab) and, when asked, saves
downloads into a folder.
"""

import contextlib
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time

CHROMIUM = os.environ.get("MOTORJIG_CHROMIUM", "/usr/bin/chromium")
CHROMEDRIVER = os.environ.get("MOTORJIG_CHROMEDRIVER", "/usr/bin/chromedriver")
HEADLESS_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage", "--window-size=1440,1000", "--disable-popup-blocking")


def browser_missing():
    """Why the browser tests cannot run here, or None."""
    for path in (CHROMIUM, CHROMEDRIVER):
        if not os.access(path, os.X_OK):
            return "%s is missing (Debian: apt-get install chromium chromium-driver)" % path
    try:
        import selenium  # noqa: F401
        import nicegui  # noqa: F401
    except ImportError as exc:
        return "%s is not installed (make setup)" % exc.name
    return None


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def _read_until(proc, needle, timeout):
    """The first stdout line of proc containing needle (lines before it are kept in proc.early)."""
    end = time.monotonic() + timeout
    proc.early = getattr(proc, "early", [])
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        proc.early.append(line)
        if needle in line:
            return line
    raise RuntimeError("%r never appeared; output so far:\n%s" % (needle, "".join(proc.early)))


_DATA_HOME = None


def data_home():
    """A folder of its own for the children's default results database (never the user's)."""
    global _DATA_HOME
    if _DATA_HOME is None:
        _DATA_HOME = tempfile.mkdtemp(prefix="motorjig-desk-data-")
    return _DATA_HOME


def _spawn(args):
    # NiceGUI switches to its own test mode (and another port) when it sees pytest's variable.
    env = {k: v for k, v in os.environ.items() if k not in ("PYTEST_CURRENT_TEST", "JIGCTL_DB")}
    env["PYTHONUNBUFFERED"] = "1"
    env["XDG_DATA_HOME"] = data_home()
    return subprocess.Popen([sys.executable] + args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env, start_new_session=True)


def start_bench(drivers="2,3", *args):
    """(process, socket URL) of `python -m motorjig.sim` without demo and pty; args: more options
    (--wiring FILE, --fault SPEC)."""
    proc = _spawn(["-m", "motorjig.sim", "--no-demo", "--no-pty", "--drivers", drivers] + list(args))
    try:
        line = _read_until(proc, "tcp: socket://", 20)
    except Exception:
        stop(proc)
        raise
    return proc, line.split("tcp:", 1)[1].strip()


def start_desk(*args):
    """(process, page URL) of `python -m motorjig.desk ARGS` on a free port (the URL as printed,
    with its ?token= when the Desk has one)."""
    proc = _spawn(["-m", "motorjig.desk", "--http-port", str(free_port())] + list(args))
    try:
        line = _read_until(proc, "MotorJig Desk: http", 40)
        url = line.split("Desk:", 1)[1].split()[0]
        wait_http(url, 30)
    except Exception:
        stop(proc)
        raise
    return proc, url


def wait_http(url, timeout):
    """Wait until url answers (the URL is printed just before the server starts listening)."""
    import urllib.request

    end = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                return r.read().decode("utf-8", "replace")
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.1)


def stop(proc):
    if proc is None or proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)


class Started(list):
    """What a test has started (processes, browsers), for ``started()`` to end."""

    def browser(self, page, **kw):
        """A Browser on page, closed with the rest."""
        b = Browser(**kw)
        self.append(b)
        b.open(page)
        return b


@contextlib.contextmanager
def started():
    """A ``Started`` list to put a test's processes in: on the way out, however the block ends,
    its browsers are closed and its processes stopped, the newest first."""
    things = Started()
    try:
        yield things
    finally:
        for thing in reversed(things):
            if isinstance(thing, Browser):
                thing.close()
            else:
                stop(thing)


class Browser:
    """A headless Chromium session with the few lookups the tests need."""

    def __init__(self, downloads=None):
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service

        self.profile = tempfile.mkdtemp(prefix="motorjig-chromium-")
        opts = webdriver.ChromeOptions()
        opts.binary_location = CHROMIUM
        for flag in HEADLESS_FLAGS:
            opts.add_argument(flag)
        opts.add_argument("--user-data-dir=%s" % self.profile)
        self.driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=opts)
        self.driver.set_page_load_timeout(30)
        self.downloads = downloads
        if downloads:
            self.driver.execute_cdp_cmd("Browser.setDownloadBehavior",
                                        {"behavior": "allow", "downloadPath": downloads})

    def close(self):
        try:
            self.driver.quit()
        finally:
            shutil.rmtree(self.profile, ignore_errors=True)

    def open(self, url):
        self.driver.get(url)
        self.wait_for(lambda: self.find("conn-state") is not None, 20, "the page did not load")

    def find(self, testid, inner=""):
        from selenium.webdriver.common.by import By

        els = self.driver.find_elements(By.CSS_SELECTOR, '[data-testid="%s"] %s' % (testid, inner))
        return els[0] if els else None

    def el(self, testid, inner=""):
        e = self.find(testid, inner)
        if e is None:
            raise AssertionError("no element with data-testid=%s %s" % (testid, inner))
        return e

    def visible(self, testid):
        """The element is on the page and shown (a closed dialog's content is not)."""
        from selenium.common.exceptions import StaleElementReferenceException

        e = self.find(testid)
        try:
            return e is not None and e.is_displayed()
        except StaleElementReferenceException:  # replaced while we looked: look again
            return False

    def text(self, testid):
        e = self.find(testid)
        return e.text if e is not None else ""

    def click(self, testid):
        self.el(testid).click()

    def tab(self, testid):
        self.click(testid)
        self.wait_for(lambda: self.el(testid).get_attribute("aria-selected") == "true" and not self.js(
            "return document.querySelectorAll('.q-tab-panels [class*=\"q-transition--\"]').length"),
            5, "tab %s shown" % testid)  # and, were the panels animated, no longer sliding in

    def type(self, testid, value):
        from selenium.webdriver.common.keys import Keys

        box = self.el(testid)  # Quasar puts the attribute on the native <input> itself
        if box.tag_name not in ("input", "textarea"):
            box = self.el(testid, "input")
        box.send_keys(Keys.CONTROL, "a")
        box.send_keys(Keys.DELETE)
        box.send_keys(str(value))

    def click_text(self, testid, text):
        """Click the first element inside testid whose text is exactly text."""
        from selenium.webdriver.common.by import By

        for e in self.el(testid).find_elements(By.XPATH, ".//*"):
            if e.text.strip() == text and e.is_displayed():
                e.click()
                return
        raise AssertionError("no %r inside %s" % (text, testid))

    def choose(self, testid, label):
        """Pick the option whose text is exactly label from the dropdown testid."""
        self.el(testid).click()
        self.wait_for(lambda: self.js("return document.querySelectorAll('.q-menu .q-item').length") > 0, 5,
                      "the choices of %s" % testid)
        found = self.js("""const item = Array.from(document.querySelectorAll('.q-menu .q-item'))
                           .find(e => e.innerText.trim() === arguments[0]);
                           if (item) item.click(); return !!item;""", label)
        if not found:
            raise AssertionError("no %r in %s" % (label, testid))
        self.wait_for(lambda: label in self.text(testid), 5, "%s chosen in %s" % (label, testid))

    def connect(self, url, what="connected"):
        """Connect the page to url (the port field and CONNECT) and wait until the header says so."""
        self.type("port", url)
        self.click("btn-connect")
        self.wait_for(lambda: self.text("conn-state") == "connected: %s @ 115200" % url, 5, what)

    def live(self):
        """The page's websocket is connected and past NiceGUI's handshake (a tab brought back to the
        front may first reconnect, or reload itself: keys pressed before that are lost)."""
        return bool(self.js("return !!(window.did_handshake && window.socket && window.socket.connected)"))

    def wait_for(self, predicate, timeout=10.0, what="condition"):
        end = time.monotonic() + timeout
        last = None
        while time.monotonic() < end:
            try:
                last = predicate()
                if last:
                    return last
            except Exception as exc:  # the page is re-rendering: try again
                last = exc
            time.sleep(0.1)
        raise AssertionError("timed out after %.0f s waiting for %s (last: %r)" % (timeout, what, last))

    def js(self, script, *args):
        return self.driver.execute_script(script, *args)

    def screenshot(self, path, clean=True):
        if clean:  # pop-up notifications would cover the view
            self.js("document.querySelectorAll('.q-notification').forEach(n => n.remove());")
        if not self.driver.save_screenshot(path):
            raise OSError("could not write the screenshot %s" % path)


# A plan with one slow move (400 000 pulses at 20 000 pps: 20 s), something to abort or stop.
LONG_MOVE_PLAN = """\
[plan]
name = "long-move"
version = "1.0"
description = "one slow move of 400 000 pulses (20 s): something to abort"

[drive]
slave = 2
protocol = [6, 8]
slave_type = 20

[[steps]]
kind = "servo"
name = "servo_on"
on = true

[[steps]]
kind = "move"
name = "long"
mode = "inc"
distance = 400000
speed = 20000
position_error_max = 0
"""


def close_dialog(b):
    b.js("""document.querySelectorAll('.q-dialog .q-btn')
            .forEach(x => { if (x.innerText.trim() === 'CLOSE') x.click(); });""")
    b.wait_for(lambda: not b.js("return document.querySelectorAll('.q-dialog__inner').length"), 5, "closed")


def upload_plan(b, path, expect):
    """Upload the plan file at path on the Test tab; ``expect`` is the page's confirmation
    ("long-move.toml uploaded: plan long-move 1.0, 2 steps")."""
    b.tab("tab-plan")
    b.click("btn-plan-upload")
    box = b.wait_for(lambda: b.find("plan-upload", 'input[type="file"]'), 5, "the upload field")
    box.send_keys(str(path))
    b.wait_for(lambda: expect in b.driver.page_source, 10, "uploaded")
    close_dialog(b)
