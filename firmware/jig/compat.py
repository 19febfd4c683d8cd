"""The one place where MicroPython-only names are looked up.

Everything else imports ``const``, the tick clock and the ``IS_MICROPYTHON`` flag
from here, so the firmware modules import unchanged under CPython.
"""

try:
    from micropython import const

    IS_MICROPYTHON = True
except ImportError:
    IS_MICROPYTHON = False

    def const(value):
        return value


import time

# MicroPython's tick counters wrap at 2**30 on 32-bit ports; CPython mimics that so
# wrap-around handling is exercised by the host tests too.
TICKS_PERIOD = const(0x40000000)
_TICKS_MASK = const(0x3FFFFFFF)
_TICKS_HALF = const(0x20000000)

if hasattr(time, "ticks_us"):
    ticks_us = time.ticks_us
    ticks_ms = time.ticks_ms
    ticks_diff = time.ticks_diff
    ticks_add = time.ticks_add
    sleep_us = time.sleep_us
    sleep_ms = time.sleep_ms
else:

    def ticks_us():
        return (time.perf_counter_ns() // 1000) & _TICKS_MASK

    def ticks_ms():
        return (time.perf_counter_ns() // 1000000) & _TICKS_MASK

    def ticks_diff(a, b):
        """Signed difference a - b of two wrapped tick values."""
        return ((a - b + _TICKS_HALF) & _TICKS_MASK) - _TICKS_HALF

    def ticks_add(a, delta):
        return (a + delta) & _TICKS_MASK

    def sleep_us(us):
        time.sleep(us / 1000000)

    def sleep_ms(ms):
        time.sleep(ms / 1000)


def load_native():
    """Return the viper helper module, or None where it cannot run as machine code.

    CPython has no viper; the WebAssembly MicroPython build rejects the decorator at
    compile time. Both fall back to the portable code paths.
    """
    if not IS_MICROPYTHON:
        return None
    try:
        from jig import native

        return native
    except Exception:  # SyntaxError/ViperTypeError/ImportError: no native emitter here
        return None


# --- the viper source as plain Python -------------------------------------------------
# jig.native is written for the viper emitter. Under CPython the same source runs as
# ordinary Python with these stand-ins (slow, for the host tests' parity checks):
# the decorator does nothing and ptrN gives indexable views of the buffer. On
# MicroPython the names are never called: the viper compiler turns ptr8(...) etc.
# into casts whatever a global of that name holds.
class micropython_shim:
    @staticmethod
    def viper(fn):
        return fn

    native = viper


def ptr8(buf):
    return buf


def ptr16(buf):
    return memoryview(buf).cast("B").cast("H")


def ptr32(buf):
    try:
        return memoryview(buf).cast("B").cast("i")
    except TypeError:  # not a buffer: an object indexed by word stands for memory (tests' registers)
        return buf


def native_source():
    """jig.native as machine code (MicroPython) or as plain Python (CPython)."""
    from jig import native

    return native


# Last: jig.native imports the names above.
NATIVE = load_native()
