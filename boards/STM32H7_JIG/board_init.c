// MotorJig STM32H7_JIG: pin states set before MicroPython starts.
//
// Runs from the reset path, long before main.py. Until the firmware configures
// the USARTs both RS-485 transceivers must listen (DE low) so a booting jig never
// drives either bus, and the relays must stay off.
#include "py/mphal.h"

static void drive_low(const machine_pin_obj_t *pin) {
    mp_hal_pin_low(pin);
    mp_hal_pin_output(pin);
}

void STM32H7_JIG_board_early_init(void) {
    drive_low(pyb_pin_UP_DE);
    drive_low(pyb_pin_DN_DE);
    drive_low(pyb_pin_RLY1);
    drive_low(pyb_pin_RLY2);
    drive_low(pyb_pin_RLY3);
    drive_low(pyb_pin_RLY4);
}
