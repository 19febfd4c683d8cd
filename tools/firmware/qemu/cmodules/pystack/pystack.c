// The qemu port does not set up a Python stack of its own; the stm32 port does (384
// words in its main.c) when a board enables MICROPY_ENABLE_PYSTACK, as STM32H7_JIG
// does. tools/firmware/test_qemu.sh builds the qemu port with the same setting and has
// mp_init() call this, so the figures and the heap checks describe the board's VM.
#include "py/runtime.h"
#include "py/pystack.h"
#include "pystack.h"

#define JIG_PYSTACK_WORDS (384)

void jig_qemu_pystack_init(void) {
    static mp_obj_t pystack[JIG_PYSTACK_WORDS];
    mp_pystack_init(pystack, &pystack[JIG_PYSTACK_WORDS]);
}
