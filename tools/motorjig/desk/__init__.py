"""MotorJig Desk: the jig's PC program as a local web page (``jigctl gui``).

``session`` holds everything the page does to the bus, as plain Python (one
``BusSession`` per server, shared by every browser tab, one lock around the
``Master``); ``forms`` checks what the operator typed; ``page`` is the NiceGUI
layout that only shows the session's state and calls its methods; ``server``
starts it all (optionally with the virtual bench in the same process).
"""
