// MicroPython's own mp_irq object and hard-IRQ dispatch (shared/runtime/mpirq.c), which
// the qemu port does not compile in: memcan's CAN hands its handler to it, as the
// board's machine.CAN does.
#include "shared/runtime/mpirq.c"
