# A user C module of the qemu build only (tools/firmware/test_qemu.sh): the stm32 port's
# Python stack for the emulated Cortex-M7, so call frames never come from the heap there
# either (boards/STM32H7_JIG enables MICROPY_ENABLE_PYSTACK; stm32's main.c sets it up).
JIG_PYSTACK_DIR := $(USERMOD_DIR)
SRC_USERMOD_C += $(JIG_PYSTACK_DIR)/pystack.c
