"""MotorJig capture: Plus-R bus traffic into pcapng, for Wireshark and for the terminal.

Modules, one job each:

* ``record``   -- the Record every source yields (bus, time, direction, wire bytes, verdict)
* ``framer``   -- a byte stream cut into records by the firmware's parser (``jig.parser``)
* ``variant``  -- Ver6 or Ver8: how a listener reads a frame it did not send
* ``pcapng``   -- the pcapng writer (one interface per bus, rotation)
* ``sniff``    -- reading a listen-only adapter (or any pyserial URL) with host timestamps
* ``jigstream`` -- the jig's own record stream (both buses, its µs clock) read into records
* ``jigport``  -- the jig's capture port: start the recording (X, S), read it, stop it (X)
* ``textview`` -- one line per record for the terminal
* ``install``  -- the dissector and the extcap into the user's Wireshark folders
* ``extcap``   -- the Wireshark extcap program (``motorjig-sniff``, ``motorjig-jig``)
* ``luagen``   -- the dissector's tables, generated from the project's Python tables
* ``command``  -- ``jigctl capture``
* ``plusr.lua`` -- the Wireshark dissector

docs/capture.md describes the file layout, the verdicts and the dissector's fields.
"""
