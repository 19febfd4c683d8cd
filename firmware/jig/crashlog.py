"""The crash log: a small text file in flash about the bridge's last crash.

A header line, the counts (all crashes, the current streak of consecutive ones,
watchdog resets), then the last exception with its traceback and the counters at
the time. main.py records a crash; the board clears the streak after a clean
minute; ``crash_summary`` is the one line a diagnostics frame shows.
`mpremote fs cat :/flash/crash.txt` prints the whole file. Nothing here touches
hardware; every function takes a path so the host tests can use a temp file.
"""

import os
import sys

from jig.flashfs import FLASH_MOUNT

CRASH_PATH = FLASH_MOUNT + "/crash.txt"
CRASH_HEADER = "MotorJig crash log"
CRASH_KEYS = ("crashes", "consecutive", "wdt_resets")


def parse_crash_counts(text):
    """(crashes, consecutive, wdt_resets) from a crash log text (zeros if none)."""
    counts = [0, 0, 0]
    if text:
        for line in text.split("\n")[:4]:
            for part in line.split():
                if "=" in part:
                    k, v = part.split("=", 1)
                    if k in CRASH_KEYS:
                        try:
                            counts[CRASH_KEYS.index(k)] = int(v)
                        except ValueError:
                            pass
    return counts[0], counts[1], counts[2]


def format_crash_log(counts, what, trace, counters=(), uptime_ms=0):
    """The crash log text; counts = (crashes, consecutive, wdt_resets)."""
    lines = [CRASH_HEADER]
    lines.append(" ".join("%s=%d" % (CRASH_KEYS[i], counts[i]) for i in range(3)))
    lines.append("last: %s (after %d ms of bridge uptime)" % (what, uptime_ms))
    if trace:
        lines.append(trace.rstrip("\n"))
    if counters:
        lines.append("counters:")
        for name, value in counters:
            lines.append("  %s=%d" % (name, value))
    return "\n".join(lines) + "\n"


def read_crash_log(path=None):
    try:
        with open(path or CRASH_PATH) as f:
            return f.read()
    except OSError:
        return ""


def _write_text(path, text):
    """Write via a temporary file and a rename: a reset mid-write keeps the old log."""
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    try:
        os.rename(tmp, path)
    except OSError:
        try:
            os.remove(path)
        except OSError:
            pass
        os.rename(tmp, path)


def exception_text(exc):
    """Traceback text of exc on MicroPython or CPython."""
    try:
        import io

        buf = io.StringIO()
        if hasattr(sys, "print_exception"):
            sys.print_exception(exc, buf)
        else:
            import traceback

            traceback.print_exception(type(exc), exc, exc.__traceback__, file=buf)
        return buf.getvalue()
    except Exception:
        return repr(exc)


def record_crash(exc=None, counters=(), uptime_ms=0, what=None, path=None, wdt=False):
    """Add a crash (an exception, or a watchdog reset) to the log; never raises.

    Returns the new (crashes, consecutive, wdt_resets), or None if the log could
    not be written.
    """
    path = path or CRASH_PATH
    try:
        crashes, streak, wdt_resets = parse_crash_counts(read_crash_log(path))
        crashes += 1
        streak += 1
        if wdt:
            wdt_resets += 1
        if what is None:
            what = "watchdog reset" if exc is None else "%s: %s" % (type(exc).__name__, exc)
        trace = exception_text(exc) if exc is not None else ""
        _write_text(path, format_crash_log((crashes, streak, wdt_resets), what, trace, counters, uptime_ms))
        return crashes, streak, wdt_resets
    except Exception:
        return None


def clear_crash_streak(path=None):
    """The bridge ran cleanly for a while: zero the consecutive-crash count."""
    path = path or CRASH_PATH
    try:
        text = read_crash_log(path)
        crashes, streak, wdt_resets = parse_crash_counts(text)
        if streak == 0:
            return False
        lines = text.split("\n")
        lines[1] = " ".join("%s=%d" % (k, v) for k, v in zip(CRASH_KEYS, (crashes, 0, wdt_resets)))
        _write_text(path, "\n".join(lines))
        return True
    except Exception:
        return False


def crash_summary(path=None):
    """Header counts and the 'last:' line of the crash log as one short line."""
    text = read_crash_log(path)
    if not text:
        return "no crash recorded"
    lines = text.split("\n")
    return (lines[1] + "; " + lines[2])[:200] if len(lines) > 2 else lines[0]
