"""Docs tables stay in step with the firmware data they describe."""

import os

from motorjig.sim import doctables


def test_docs_tables_match_the_firmware_data():
    """docs/bridge.md, parameters.md, diagnostics.md embed tables generated from the code."""
    for rel in doctables.TABLES:
        with open(os.path.join(doctables.ROOT, rel)) as f:
            text = f.read()
        assert doctables.expected(rel, text) == text, "%s is stale: python -m motorjig.sim.doctables --write" % rel
