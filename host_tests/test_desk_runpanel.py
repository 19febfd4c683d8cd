"""The Test tab's measurement lines: which ones the page marks as bad."""

from motorjig.desk.runpanel import _mline


def test_a_skipped_measurement_is_not_shown_as_a_failure():
    """An abs move to where the axis already is leaves duration_ratio out (SKIPPED, no value)."""
    m = {"name": "duration_ratio", "value": None, "unit": "", "limits": "0.85 <= x <= 1.15", "outcome": "SKIPPED"}
    text, bad = _mline(m)
    assert not bad and "duration_ratio" in text
    assert _mline(dict(m, value=1.3, outcome="FAIL"))[1]
    assert not _mline(dict(m, value=1.0, outcome="PASS"))[1]
