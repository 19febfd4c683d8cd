# A user C module of the qemu build only (tools/firmware/test_qemu.sh): the board's CAN port
# (machine.CAN on FDCAN1) and its SLCAN USB CDC port as C models, for
# tools/firmware/qemu/can_suite.py (see memcan.c).
JIG_MEMCAN_DIR := $(USERMOD_DIR)
SRC_USERMOD_C += $(JIG_MEMCAN_DIR)/memcan.c $(JIG_MEMCAN_DIR)/mpirq_inc.c
