"""The board's boot pieces that need no hardware: jig.safeboot, jig.crashlog, jig.flashfs.

The safe-boot decision and the debounced SAFE button (any object with
``value()`` is a pin), the crash log's counts, streak and summary in a temp
file, and the flash mount: mounted as is, formatted when the mount fails, "none"
without a block device or when formatting fails too (``os.mount`` and
``os.VfsLfs2`` are stood in for: CPython has neither).
"""

import os
import sys

import pytest

from jig import crashlog, flashfs, safeboot


# --- safe boot ---------------------------------------------------------------------------
def test_safe_boot_decision():
    assert safeboot.decide_boot(False, 0) == safeboot.MODE_BRIDGE
    assert safeboot.decide_boot(True, 0) == safeboot.MODE_SAFE_BUTTON
    assert safeboot.decide_boot(False, safeboot.SAFE_AFTER_CRASHES - 1) == safeboot.MODE_BRIDGE
    assert safeboot.decide_boot(False, 3) == "safe: the bridge crashed 3 times in a row"
    assert safeboot.decide_boot(True, 7) == safeboot.MODE_SAFE_BUTTON  # the button says why first


class ScriptedPin:
    def __init__(self, levels):
        self.levels = list(levels)

    def value(self):
        return self.levels.pop(0)


def test_safe_button_must_read_active_on_every_sample(monkeypatch):
    monkeypatch.setattr(safeboot, "sleep_ms", lambda ms: None)
    assert safeboot.button_held(ScriptedPin([0] * 5), 0) is True
    assert safeboot.button_held(ScriptedPin([0, 0, 1, 0, 0]), 0) is False  # a bounce
    assert safeboot.button_held(ScriptedPin([1] * 5), 1) is True  # active high
    assert safeboot.button_held(ScriptedPin([1] * 5), 0) is False


# --- crash log -----------------------------------------------------------------------------
def test_crash_log_counts_streak_and_clears(tmp_path):
    path = str(tmp_path / "crash.txt")
    try:
        raise ValueError("boom")
    except ValueError as e:
        assert crashlog.record_crash(e, (("forwards", 12), ("replies", 11)), 1234, path=path) == (1, 1, 0)
    text = crashlog.read_crash_log(path)
    assert text.startswith(crashlog.CRASH_HEADER + "\ncrashes=1 consecutive=1 wdt_resets=0\n")
    assert "ValueError: boom" in text and "forwards=12" in text and "1234 ms" in text
    assert "Traceback" in text
    assert crashlog.record_crash(wdt=True, path=path) == (2, 2, 1)
    assert crashlog.parse_crash_counts(crashlog.read_crash_log(path)) == (2, 2, 1)
    assert crashlog.crash_summary(path) == (
        "crashes=2 consecutive=2 wdt_resets=1; last: watchdog reset (after 0 ms of bridge uptime)"
    )
    assert crashlog.clear_crash_streak(path) is True
    assert crashlog.parse_crash_counts(crashlog.read_crash_log(path)) == (2, 0, 1)
    assert crashlog.clear_crash_streak(path) is False
    assert not os.path.exists(path + ".tmp")


def test_crash_log_missing_or_garbage(tmp_path):
    path = str(tmp_path / "none.txt")
    assert crashlog.parse_crash_counts(crashlog.read_crash_log(path)) == (0, 0, 0)
    assert crashlog.crash_summary(path) == "no crash recorded"
    assert crashlog.parse_crash_counts("junk\ncrashes=x consecutive=2\n") == (0, 2, 0)
    assert crashlog.clear_crash_streak(path) is False


def test_record_crash_never_raises(tmp_path):
    path = str(tmp_path / "no" / "such" / "dir" / "crash.txt")
    assert crashlog.record_crash(RuntimeError("x"), path=path) is None


def test_crash_log_lives_on_the_flash():
    assert crashlog.CRASH_PATH == flashfs.FLASH_MOUNT + "/crash.txt"


# --- flash mount ---------------------------------------------------------------------------
class FakeVfs:
    """os.VfsLfs2 stand-in: mounting a device marked blank fails until mkfs."""

    made = []

    def __init__(self, bdev):
        self.bdev = bdev
        FakeVfs.made.append(self)

    @staticmethod
    def mkfs(bdev):
        if bdev.get("broken"):
            raise OSError(5)
        bdev["blank"] = False
        bdev["formatted"] = True


@pytest.fixture
def vfs(monkeypatch, tmp_path):
    mounts = []

    def mount(fs, path):
        if fs.bdev.get("blank"):
            raise OSError(19)
        mounts.append(path)

    FakeVfs.made = []
    monkeypatch.setattr(os, "VfsLfs2", FakeVfs, raising=False)
    monkeypatch.setattr(os, "mount", mount, raising=False)
    monkeypatch.setattr(os, "chdir", lambda path: None)
    monkeypatch.setattr(flashfs, "FLASH_MOUNT", str(tmp_path / "flash-not-mounted"))
    monkeypatch.setattr(sys, "path", list(sys.path))
    return mounts


def test_mount_keeps_a_good_filesystem(vfs):
    bdev = {"blank": False}
    assert flashfs.mount_flash(bdev) == "mounted"
    assert vfs == [flashfs.FLASH_MOUNT] and "formatted" not in bdev
    assert flashfs.FLASH_MOUNT in sys.path and flashfs.FLASH_MOUNT + "/lib" in sys.path


def test_mount_formats_a_blank_flash(vfs):
    bdev = {"blank": True}
    assert flashfs.mount_flash(bdev) == "formatted"
    assert bdev["formatted"] and vfs == [flashfs.FLASH_MOUNT]


def test_mount_gives_none_when_it_cannot(vfs):
    assert flashfs.mount_flash(None) == "none"
    assert flashfs.mount_flash({"blank": True, "broken": True}) == "none"
    assert vfs == []


def test_mount_does_nothing_when_already_mounted(vfs, monkeypatch, tmp_path):
    monkeypatch.setattr(flashfs, "FLASH_MOUNT", str(tmp_path))  # exists: mounted
    assert flashfs.mount_flash({"blank": True}) == "mounted"
    assert vfs == [] and FakeVfs.made == []
