# MotorJig STM32H7_JIG: STM32H743VIT6 (LQFP100, 2 MB flash, 1 MB RAM).
# Build with:  make firmware MICROPY_DIR=/path/to/micropython   (from the project root)

USE_MBOOT ?= 0

# MCU
MCU_SERIES = h7
CMSIS_MCU = STM32H743xx
MICROPY_FLOAT_IMPL = double
AF_FILE = boards/stm32h743_af.csv

# No bootloader: the image starts at the beginning of flash. The ROM DFU bootloader
# (BOOT0 high, or machine.bootloader()) is used to load it over USB.
LD_FILES = boards/stm32h743.ld boards/common_basic.ld
TEXT0_ADDR = 0x08000000

# Filesystem: littlefs v2 only, on the internal flash region the linker script
# reserves (sectors 4-7 of bank 2, 512 KB). FAT is off, so a blank board has no
# filesystem until the firmware formats one (jig.board.mount_flash does that).
MICROPY_VFS_FAT = 0
MICROPY_VFS_LFS2 = 1

# Keep the UART RX interrupt (and the vector table) in RAM so received bytes are
# not lost while a flash sector is erased or written (parameter save, crash log).
MICROPY_HW_ENABLE_ISR_UART_FLASH_FUNCS_IN_RAM = 1

# No networking: no Ethernet, lwIP, TLS, Bluetooth. The stm32 port then needs only
# the lib/stm32lib and lib/tinyusb submodules.
MICROPY_PY_LWIP = 0
MICROPY_PY_SSL = 0
MICROPY_SSL_MBEDTLS = 0
MICROPY_PY_NETWORK = 0
MICROPY_PY_BLUETOOTH = 0

# Frozen code: the jig firmware package and main.py (see manifest.py). The frozen
# bytecode and viper code target the Cortex-M7 with double-precision FPU.
# The port's default for H7 is plain armv7m; `override` makes this board's choice
# stick even when the port's stm32.mk assigns it afterwards. tools/firmware/build_firmware.sh
# also passes MPY_CROSS_FLAGS=-march=armv7emdp on the command line.
FROZEN_MANIFEST ?= $(BOARD_DIR)/manifest.py
override MPY_CROSS_MCU_ARCH_h7 = armv7emdp
