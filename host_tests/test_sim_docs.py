"""Docs tables stay in step with the firmware data they describe."""

import os

import pytest

from motorjig.sim import doctables


@pytest.mark.parametrize("rel", sorted(doctables.TABLES))
def test_docs_tables_match_the_firmware_data(rel):
    """docs/bridge.md, parameters.md, diagnostics.md and station.md embed tables generated from the code."""
    with open(os.path.join(doctables.ROOT, rel)) as f:
        text = f.read()
    assert doctables.expected(rel, text) == text, "%s is stale: python -m motorjig.sim.doctables --write" % rel


def test_missing_markers_are_an_error():
    with pytest.raises(ValueError):
        doctables.expected("docs/bridge.md", "<!-- BEGIN params -->\n<!-- END params -->\n")
