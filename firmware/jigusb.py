"""USB of the STM32H7_JIG image: three CDC ports, the REPL, the capture stream, SLCAN.

The stm32 port runs this frozen file before boot.py (the board sets
MICROPY_BOARD_FROZEN_BOOT_FILE), while USB is not started yet: the first port
stays the REPL (mpremote, `make deploy`), the second carries the recording of
the buses (jig.capture), the third the CAN port's SLCAN session (jig.canport;
``jig.board.Board`` opens both). A build with fewer CDC ports gets two, or the
REPL only. Under CPython, or on a port without ``pyb``, importing it does nothing.
"""

try:
    import pyb
except ImportError:
    pyb = None

if pyb is not None and hasattr(pyb, "usb_mode"):
    for _mode in ("VCP+VCP+VCP", "VCP+VCP"):
        try:
            pyb.usb_mode(_mode)
            break
        except (OSError, ValueError):  # fewer CDC ports in this build: try fewer
            pass
