# A user C module of the qemu build only (tools/firmware/test_qemu.sh): the qemu suite's HAL
# port in C (see memport.c for why).
JIG_MEMPORT_DIR := $(USERMOD_DIR)
SRC_USERMOD_C += $(JIG_MEMPORT_DIR)/memport.c
