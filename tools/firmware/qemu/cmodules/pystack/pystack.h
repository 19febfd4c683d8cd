// Force-included into every C file of the qemu build by tools/firmware/test_qemu.sh
// (-include): the Python stack of the STM32H7_JIG board, set up from mp_init().
#define MICROPY_ENABLE_PYSTACK (1)
#define MICROPY_PORT_INIT_FUNC jig_qemu_pystack_init()
void jig_qemu_pystack_init(void);
