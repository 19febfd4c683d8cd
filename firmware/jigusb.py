"""USB of the STM32H7_JIG image: two CDC ports, the REPL and the capture stream.

The stm32 port runs this frozen file before boot.py (the board sets
MICROPY_BOARD_FROZEN_BOOT_FILE), while USB is not started yet: the first port
stays the REPL (mpremote, `make deploy`), the second carries the recording of
both RS-485 buses (jig.capture; ``jig.board.capture_port`` opens it). Under
CPython, or on a port without ``pyb``, importing it does nothing.
"""

try:
    import pyb
except ImportError:
    pyb = None

if pyb is not None and hasattr(pyb, "usb_mode"):
    try:
        pyb.usb_mode("VCP+VCP")
    except (OSError, ValueError):  # a build with one CDC port: the REPL only
        pass
