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


class Emcy:
    """An emergency a CiA 402 drive sent (on CAN or in CoE): ``t`` its time, ``code``, ``register``, ``text``."""

    __slots__ = ("t", "code", "register", "text")

    def __init__(self, t, code, register):
        from motorjig.can import cia301

        self.t, self.code, self.register = t, code, register
        self.text = "EMCY 0x%04X %s (error register 0x%02X)" % (code, cia301.emcy_name(code), register)


def cia301_identity(read):
    """What a CiA 301 device says it is, by ``read(index, sub)``: device type 0x1000, the names and
    versions 0x1008-0x100A (None when a device has not the optional ones) and the identity 0x1018."""
    ident = {"device_type": read(0x1000, 0)}
    for index, name in ((0x1008, "device_name"), (0x1009, "hardware_version"), (0x100A, "software_version")):
        try:
            ident[name] = read(index, 0)
        except JigError:
            ident[name] = None
    for sub, name in ((1, "vendor_id"), (2, "product_code"), (3, "revision"), (4, "serial")):
        ident[name] = read(0x1018, sub)
    return ident


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
