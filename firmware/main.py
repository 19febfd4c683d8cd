"""Boot entry of the STM32H7_JIG image: safe-boot check, then the bridge.

Frozen into the image (it runs even with an empty filesystem). Order:

1. room for interrupt exception reports, littlefs mounted at /flash (formatted on
   a blank board);
2. a watchdog reset since the last boot is logged as a crash;
3. safe boot (jig.safeboot) -- SAFE button held at reset, or SAFE_AFTER_CRASHES
   crashes in a row without a clean minute of bridging in between: nothing is
   started, both RS-485 drivers stay off the bus, the USB REPL is free (error +
   heartbeat LEDs on);
4. otherwise ``jig.app.App(board).run()`` forever.

If the bridge raises, the exception and the counters go to the crash log
(jig.crashlog, /flash/crash.txt) and the board resets (a clean restart beats a
half-working bridge). Ctrl-C on the REPL stops the bridge and leaves the REPL,
with the watchdog kept fed by a timer.

Under CPython (no ``machine``) importing this file does nothing; the host tests
call ``main()`` with fake hardware modules.
"""

from jig.compat import sleep_ms

RESET_DELAY_MS = 500


def counter_pairs(app):
    """(name, value) of every diagnostics counter, for the crash log."""
    if app is None:
        return ()
    try:
        from jig import diag

        values = app.counter_values([0] * diag.N_WIRE)
        return tuple(zip(diag.WIRE_NAMES, values))
    except Exception:
        return ()


def main():
    import machine

    from jig import board, crashlog, safeboot

    fs = board.early_boot()
    if board.watchdog_reset_happened():
        crashlog.record_crash(wdt=True)
    _crashes, streak, _wdt = crashlog.parse_crash_counts(crashlog.read_crash_log())
    pin, active = board.safe_button()
    mode = safeboot.decide_boot(safeboot.button_held(pin, active), streak)
    hal = board.Board()
    if mode != safeboot.MODE_BRIDGE:
        hal.error_led(True)
        hal.heartbeat(True)
        print("MotorJig %s -- bridge not started, REPL free (flash: %s)." % (mode, fs))
        print("Crash log: %s" % crashlog.crash_summary())
        return mode
    app = None
    try:
        from jig.app import App

        app = App(hal)
        app.run()
    except KeyboardInterrupt:
        hal.keep_watchdog_fed()
        print("MotorJig bridge stopped (Ctrl-C); REPL free, watchdog fed by a timer.")
        return "stopped"
    except Exception as exc:
        hal.error_led(True)
        # (the board's count: ticks_diff(ticks_ms(), t0) is wrong after 6.2 days)
        crashlog.record_crash(exc, counter_pairs(app), hal.uptime_ms())
        print("MotorJig bridge crashed: %s" % crashlog.crash_summary())
        sleep_ms(RESET_DELAY_MS)
        machine.reset()
    return "crashed"


try:
    import machine as _machine  # noqa: F401  (present on the board only)
except ImportError:
    _machine = None

if _machine is not None:
    main()
