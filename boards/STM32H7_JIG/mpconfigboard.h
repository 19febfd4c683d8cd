// MotorJig STM32H7_JIG: RS-485 bridge jig built around an STM32H743VIT6
// (LQFP100, 2 MB flash, 1 MB RAM, Cortex-M7 with double-precision FPU).
// Wiring and rationale: docs/board.md of the MotorJig project.

#define MICROPY_HW_BOARD_NAME       "MotorJig STM32H7_JIG"
#define MICROPY_HW_MCU_NAME         "STM32H743VI"
#define MICROPY_HW_FLASH_FS_LABEL   "motorjig"

// Peripherals the jig uses. No SD card, DAC or networking.
#define MICROPY_HW_ENABLE_RTC       (1)
#define MICROPY_HW_ENABLE_RNG       (1)
#define MICROPY_HW_ENABLE_ADC       (1)
#define MICROPY_HW_ENABLE_DAC       (0)
#define MICROPY_HW_ENABLE_USB       (1)
#define MICROPY_HW_ENABLE_SDCARD    (0)
#define MICROPY_HW_HAS_FLASH        (1)

// Python call frames on a fixed stack (stm32's main.c gives it 384 words) instead of
// the heap: otherwise every call whose frame exceeds 11 words allocates and frees heap
// memory, and the bridge's main loop would feed the garbage collector.
#define MICROPY_ENABLE_PYSTACK      (1)
// The SAFE button belongs to the firmware (main.py decides safe boot), so the
// port's own reset-time boot-mode menu on the user switch is not used.
#define MICROPY_HW_HAS_SWITCH       (0)
#define MICROPY_HW_RTC_USE_LSE      (1)

// --- Clocks ---------------------------------------------------------------------
// HSE: 25 MHz crystal. PLL1: 25 MHz / M5 = 5 MHz reference (VCI range 2: 4-8 MHz),
// x N160 = 800 MHz VCO (wide range 192-836 MHz), / P2 = SYSCLK 400 MHz.
// 400 MHz and not 480 MHz: 400 MHz is allowed on every STM32H743 silicon revision
// (rev Y stops at 400 MHz; 480 MHz needs rev V and voltage scale VOS0, which also
// lowers the allowed junction temperature). A forwarded byte at 921 600 baud
// still leaves ~4 300 CPU cycles, and the bridge needs far fewer.
// The port's H7 defaults then give HCLK/AXI = 200 MHz and APB1..4 = 100 MHz, so
// USART2/3 run from a 100 MHz kernel clock (115 200 baud: BRR 868, 0.01 % error;
// 921 600 baud: BRR 109, 0.45 % error).
#define MICROPY_HW_CLK_PLLM         (5)
#define MICROPY_HW_CLK_PLLN         (160)
#define MICROPY_HW_CLK_PLLP         (2)
#define MICROPY_HW_CLK_PLLQ         (4)     // 200 MHz for SPI/ADC kernel clocks
#define MICROPY_HW_CLK_PLLR         (2)
#define MICROPY_HW_CLK_PLLVCI       (RCC_PLL1VCIRANGE_2)
#define MICROPY_HW_CLK_PLLVCO       (RCC_PLL1VCOWIDE)
#define MICROPY_HW_CLK_PLLFRAC      (0)

// PLL3 makes the 48 MHz USB clock: 25 / M5 = 5 MHz, x N48 = 240 MHz, / Q5 = 48 MHz.
#define MICROPY_HW_CLK_PLL3M        (5)
#define MICROPY_HW_CLK_PLL3N        (48)
#define MICROPY_HW_CLK_PLL3P        (2)
#define MICROPY_HW_CLK_PLL3Q        (5)
#define MICROPY_HW_CLK_PLL3R        (2)
#define MICROPY_HW_CLK_PLL3VCI      (RCC_PLL3VCIRANGE_2)
#define MICROPY_HW_CLK_PLL3VCO      (RCC_PLL3VCOWIDE)
#define MICROPY_HW_CLK_PLL3FRAC     (0)

// Flash wait states for a 200 MHz AXI clock: RM0433 asks for at least 2 at VOS1;
// 4 leaves margin across supply voltage and matches ST's NUCLEO-H743ZI at the same
// clocks. The L1 instruction cache hides almost all of the cost.
#define MICROPY_HW_FLASH_LATENCY    FLASH_LATENCY_4

// --- RS-485 ports ------------------------------------------------------------------
// Upstream (connector J2 "PC"): USART2, transceiver U2. DE on PD4, the pin whose
// AF7 is USART2_RTS/USART2_DE, so the USART can drive it in hardware.
#define MICROPY_HW_UART2_TX         (pyb_pin_UP_TX)     // PD5 AF7
#define MICROPY_HW_UART2_RX         (pyb_pin_UP_RX)     // PD6 AF7
#define MICROPY_HW_UART2_RTS        (pyb_pin_UP_DE)     // PD4 AF7 (DE)
// Downstream (connector J3 "DRIVERS"): USART3, transceiver U3. DE on PD12 (AF7
// USART3_RTS/USART3_DE).
#define MICROPY_HW_UART3_TX         (pyb_pin_DN_TX)     // PD8 AF7
#define MICROPY_HW_UART3_RX         (pyb_pin_DN_RX)     // PD9 AF7
#define MICROPY_HW_UART3_RTS        (pyb_pin_DN_DE)     // PD12 AF7 (DE)

// --- CAN port ------------------------------------------------------------------------
// Connector J4 "CAN": FDCAN1, 3.3 V transceiver U4 (TCAN334 / SN65HVD230 class), 120 ohm
// termination by jumper. PD1/PD0 (AF9), the pins upstream's NUCLEO_H743ZI uses, so
// the same machine.CAN(1) works on both. The name makes machine.CAN part of the image.
#define MICROPY_HW_CAN1_NAME        "FDCAN1"
#define MICROPY_HW_CAN1_TX          (pin_D1)            // PD1 AF9 FDCAN1_TX
#define MICROPY_HW_CAN1_RX          (pin_D0)            // PD0 AF9 FDCAN1_RX

// --- LEDs (active high). LED1 is the one the port blinks on a fatal error. ----------
#define MICROPY_HW_LED1             (pyb_pin_LED_ERR)       // PE4 red: error
#define MICROPY_HW_LED2             (pyb_pin_LED_HB)        // PE2 green: heartbeat
#define MICROPY_HW_LED3             (pyb_pin_LED_TRAFFIC)   // PE3 yellow: bus traffic
#define MICROPY_HW_LED_ON(pin)      (mp_hal_pin_high(pin))
#define MICROPY_HW_LED_OFF(pin)     (mp_hal_pin_low(pin))

// --- USB: full-speed device on PA11/PA12 (REPL, mpremote; ROM DFU for flashing) ----
#define MICROPY_HW_USB_FS           (1)
#define MICROPY_HW_USB_VBUS_DETECT_PIN (pyb_pin_USB_VBUS)  // PA9
// The flash holds littlefs, which a PC cannot mount: USB is CDC (REPL) only.
#define MICROPY_HW_USB_MSC          (0)
// Three CDC ports: the REPL, the stream of records of the buses (jig.capture), and
// the CAN port's SLCAN session (jig.canport). USB starts in that mode from the
// frozen boot file, which the port runs before boot.py.
#define MICROPY_HW_USB_CDC_NUM      (3)
#define MICROPY_BOARD_FROZEN_BOOT_FILE "jigusb.py"
#define MICROPY_HW_USB_MANUFACTURER_STRING "MotorJig"
#define MICROPY_HW_USB_PRODUCT_FS_STRING   "MotorJig STM32H7_JIG RS-485 bridge"

// Put the board in a defined state before MicroPython starts: DE low (receivers
// on, drivers off the bus) and relays off, whatever happens later.
#define MICROPY_BOARD_EARLY_INIT    STM32H7_JIG_board_early_init
void STM32H7_JIG_board_early_init(void);
