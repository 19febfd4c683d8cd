"""The boot decision: run the bridge, or stay in safe boot with the REPL free.

Safe boot when the SAFE button is held at reset (debounced here; the board
supplies the pin) or after SAFE_AFTER_CRASHES crashes in a row -- a streak the
crash log counts and the board clears after CLEAN_RUN_MS of clean bridging.
"""

from jig.compat import const, sleep_ms

SAFE_AFTER_CRASHES = const(3)  # consecutive crashes that force safe boot
CLEAN_RUN_MS = const(60000)  # bridge uptime after which a crash streak is over

MODE_BRIDGE = "bridge"
MODE_SAFE_BUTTON = "safe: SAFE button held at reset"
MODE_SAFE_CRASHES = "safe: the bridge crashed %d times in a row"


def button_held(pin, active, samples=5):
    """True if pin reads its active level on every one of samples reads, 1 ms apart."""
    sleep_ms(2)  # let the pull-up charge the line
    held = 0
    for _ in range(samples):
        if pin.value() == active:
            held += 1
        sleep_ms(1)
    return held == samples


def decide_boot(button_is_held, consecutive_crashes):
    """The boot mode: MODE_BRIDGE, or a MODE_SAFE_* reason string."""
    if button_is_held:
        return MODE_SAFE_BUTTON
    if consecutive_crashes >= SAFE_AFTER_CRASHES:
        return MODE_SAFE_CRASHES % consecutive_crashes
    return MODE_BRIDGE
