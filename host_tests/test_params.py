"""Jig parameter table, RAM/ROM, atomic save and power loss at every byte."""

import pytest

from jig import params as P
from motorjig.sim import PowerLoss, SimFS

PATH = "/flash/jigparams.bin"


def test_table_is_consistent():
    assert len(P.TABLE) == P.COUNT
    names = set()
    for i, (num, name, unit, lo, hi, default, when) in enumerate(P.TABLE):
        assert num == i and name not in names
        names.add(name)
        assert lo <= default <= hi and P.valid(num, default)
        assert when in (P.IMMEDIATE, P.RESTART)
    assert P.FILE_SIZE == 4 + 1 + 4 * P.COUNT + 2


def test_ranges_and_unknown_numbers():
    pr = P.Params()
    assert not pr.set(P.COUNT, 1)
    assert not pr.set(P.P_SLAVE_ID, 16)
    assert not pr.set(P.P_UP_BAUD, 100000)  # in range but not a baud rate
    assert pr.set(P.P_UP_BAUD, 921600) and pr.get(P.P_UP_BAUD) == 921600
    assert pr.get_rom(P.P_UP_BAUD) == 115200  # ROM unchanged until saved
    assert not pr.set(P.P_REPLY_TIMEOUT_MS, 0) and pr.get(P.P_REPLY_TIMEOUT_MS) == 50


def test_missing_file_gives_defaults():
    pr = P.Params(SimFS(), PATH)
    assert pr.load() is False
    assert pr.ram == [row[5] for row in P.TABLE]


def test_save_and_load_roundtrip():
    fs = SimFS()
    pr = P.Params(fs, PATH)
    pr.set(P.P_SLAVE_ID, 7)
    pr.set(P.P_SAFETY_TIMEOUT_MS, 1500)
    assert pr.save()
    assert pr.get_rom(P.P_SLAVE_ID) == 7
    assert set(fs.files) == {PATH}  # temp file renamed away
    pr2 = P.Params(fs, PATH)
    assert pr2.load() is True
    assert pr2.get(P.P_SLAVE_ID) == 7 and pr2.get_rom(P.P_SAFETY_TIMEOUT_MS) == 1500


@pytest.mark.parametrize("offset", [0, 3, 4, 5, 20, P.FILE_SIZE - 2, P.FILE_SIZE - 1])
def test_corrupt_file_gives_defaults(offset):
    fs = SimFS()
    pr = P.Params(fs, PATH)
    pr.set(P.P_SLAVE_ID, 9)
    pr.save()
    data = bytearray(fs.files[PATH])
    data[offset] ^= 0x10
    fs.files[PATH] = bytes(data)
    pr2 = P.Params(fs, PATH)
    assert pr2.load() is False and pr2.get(P.P_SLAVE_ID) == 1


def test_truncated_and_oversized_files_rejected():
    fs = SimFS()
    pr = P.Params(fs, PATH)
    pr.save()
    good = fs.files[PATH]
    for bad in (good[:-1], good + b"\x00", b"", b"MJP1"):
        fs.files[PATH] = bad
        assert P.Params(fs, PATH).load() is False


def _power_loss_cases(replace_ok):
    old = {P.P_SLAVE_ID: 3, P.P_REPLY_TIMEOUT_MS: 80}
    new = {P.P_SLAVE_ID: 12, P.P_REPLY_TIMEOUT_MS: 200, P.P_SAFETY_ACTION: 1}
    fs0 = SimFS()
    fs0.replace_ok = replace_ok
    pr = P.Params(fs0, PATH)
    for k, v in old.items():
        pr.set(k, v)
    pr.save()
    base = dict(fs0.files)
    old_vals = list(pr.ram)
    for k, v in new.items():
        pr.set(k, v)
    new_vals = list(pr.ram)
    return base, old_vals, new_vals, new


@pytest.mark.parametrize("replace_ok", [True, False], ids=["atomic-rename", "remove-then-rename"])
def test_power_loss_at_every_byte_offset(replace_ok):
    base, old_vals, new_vals, new = _power_loss_cases(replace_ok)
    outcomes = set()
    for cut in range(P.FILE_SIZE + 1):
        for step in ("write", "after-write", "after-remove"):
            fs = SimFS()
            fs.replace_ok = replace_ok
            fs.files = dict(base)
            pr = P.Params(fs, PATH)
            pr.load()
            for k, v in new.items():
                pr.set(k, v)
            if step == "write":
                fs.fail_after = cut
                try:
                    pr.save()
                    finished = True
                except PowerLoss:
                    finished = False
                if cut < P.FILE_SIZE:
                    assert not finished
            else:
                if cut:
                    continue
                orig_rename = fs.rename
                orig_remove = fs.remove

                def dying_rename(src, dst, _o=orig_rename):
                    if step == "after-write":
                        raise PowerLoss()
                    return _o(src, dst)

                def dying_remove(path, _o=orig_remove):
                    _o(path)
                    if step == "after-remove":
                        raise PowerLoss()

                fs.rename = dying_rename
                fs.remove = dying_remove
                try:
                    pr.save()
                except PowerLoss:
                    pass
            # power back on
            fs2 = SimFS()
            fs2.files = dict(fs.files)
            after = P.Params(fs2, PATH)
            assert after.load() is True, (cut, step)
            assert after.ram in (old_vals, new_vals), (cut, step)
            outcomes.add("new" if after.ram == new_vals else "old")
    assert outcomes == {"old", "new"}


def test_filefs_on_a_real_directory(tmp_path):
    fs = P.FileFS()
    path = str(tmp_path / "p.bin")
    assert fs.read_into(path, bytearray(8)) == -1
    pr = P.Params(fs, path)
    pr.set(P.P_DE_PRE_US, 33)
    assert pr.save()
    pr.set(P.P_DE_PRE_US, 44)
    assert pr.save()  # rename over an existing file
    again = P.Params(fs, path)
    assert again.load() and again.get(P.P_DE_PRE_US) == 44
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.bin"]
