# MotorJig STM32H7_JIG frozen modules: the `jig` firmware package and the boot
# entry main.py, both from the project's firmware/ folder (two levels above this
# board folder). Nothing from micropython-lib and no asyncio: the firmware uses
# neither.
freeze("$(BOARD_DIR)/../../firmware", ("main.py",))
package("jig", base_path="$(BOARD_DIR)/../../firmware")
