"""The drive interface the station's steps speak to, whatever the drive's protocol.

A step kind does its work through one ``Drive`` object, the plug's ``bus.drive``, which
its drive kind (``station.kinds``, the table of kinds) opens for the run; each kind has its
own implementation in its own module.

Every implementation has:

* ``protocol``: its kind's name in the table of kinds; ``label``: the drive as the records name it
  ("slave 2", "node 5");
* ``identify()`` -> {name: value} of what the drive says it is;
* ``enable(on)`` -> {"state", "transitions": [(name, seconds)]}: switched on (operation
  enabled) or off; ``fault_reset()``; ``fault()`` -> the drive's fault code (0: none);
* ``quick_stop()`` / ``halt()``: stop a motion (the protocol's emergency and ramped stops);
* ``bus_health()`` -> {name: value} of the bus's counters over the run;
* ``make_safe(emergency=False)`` -> the problems met (texts): stop the axis and switch it
  off, trying each action whatever the one before did (the end of every run that did not
  pass, and every interrupted one);
* ``close()``.

The moving steps sample the axis through a trace (``station.sampling``): rows of
(t on the jig's clock, command/demand, actual, velocity) and the instants of the step's
commands on the same clock.
"""


from motorjig.errors import JigError


class DriveFault(Exception):
    """The drive reported a fault during a step (a CiA 402 EMCY): the step fails with the code
    and its meaning, ``code`` and ``text``."""

    def __init__(self, code, text):
        super().__init__(text)
        self.code, self.text = code, text


class SdoRefused(JigError):
    """The drive answered an object access (an SDO, on CAN or in CoE) with an abort: a definite answer
    about the drive (a step can judge it), unlike silence (the link). ``code`` is the CiA 301 abort code."""

    def __init__(self, message, code):
        super().__init__(message)
        self.code = code


class Drive:
    """The interface (see the module's doc); implementations override every method."""

    protocol = ""
    label = ""
    # what make_safe(emergency=True) does, in the words of the drive's protocol (for messages)
    emergency_words = "stop and switch off"

    def identify(self):
        raise NotImplementedError

    def enable(self, on):
        raise NotImplementedError

    def fault_reset(self):
        raise NotImplementedError

    def fault(self):
        raise NotImplementedError

    def quick_stop(self):
        raise NotImplementedError

    def halt(self):
        raise NotImplementedError

    def bus_health(self):
        raise NotImplementedError

    def make_safe(self, emergency=False):
        raise NotImplementedError

    def close(self):
        pass
