// MotorJig STM32H7_JIG: ST HAL configuration (oscillator values).
#ifndef MICROPY_INCLUDED_STM32H7XX_HAL_CONF_H
#define MICROPY_INCLUDED_STM32H7XX_HAL_CONF_H

// 25 MHz crystal on PH0/PH1 (OSC_IN/OSC_OUT).
#define HSE_VALUE (25000000)
// 32.768 kHz crystal on PC14/PC15 for the RTC (crash-log time stamps).
#define LSE_VALUE (32768)
// No external I2S clock input on this board; the HAL wants a value.
#define EXTERNAL_CLOCK_VALUE (12288000)

#define HSE_STARTUP_TIMEOUT (5000)
#define LSE_STARTUP_TIMEOUT (5000)

#include "boards/stm32h7xx_hal_conf_base.h"

#endif // MICROPY_INCLUDED_STM32H7XX_HAL_CONF_H
