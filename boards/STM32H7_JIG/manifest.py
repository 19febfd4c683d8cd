"""Frozen modules of the STM32H7_JIG image: the `jig` firmware package, main.py and
jigusb.py (the two USB CDC ports, run before boot.py).

Both come from the project's firmware/ folder, two levels above this board folder.
Nothing from micropython-lib and no asyncio: the firmware uses neither.
"""

freeze("$(BOARD_DIR)/../../firmware", ("main.py", "jigusb.py"))
package("jig", base_path="$(BOARD_DIR)/../../firmware")
