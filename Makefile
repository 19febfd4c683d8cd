# MotorJig: build, test, simulate and flash. `make help` lists the targets.
#
#   make            set up, then flash the jig if one is attached, else start the virtual bench
#   make test       set up and run every host-side check (what CI runs)

PY          := .venv/bin/python
SIM_ARGS    ?=
MICROPY_DIR ?=
BUILD       ?= $(CURDIR)/build/STM32H7_JIG
BOARD_DIR   := $(CURDIR)/boards/STM32H7_JIG

.DEFAULT_GOAL := run
.PHONY: help setup run test check-mpy bench docs screenshots sim firmware flash deploy test-qemu clean

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'

setup: ## create .venv and install everything the host side needs
	@tools/setup.sh

run: setup ## the main job: flash an attached jig, otherwise run the virtual bench
	@$(PY) tools/flash.py auto

test: setup check-mpy ## compile firmware for Cortex-M7, then run all host tests
	@$(PY) -m pytest

check-mpy: setup ## compile every firmware module with mpy-cross -march=armv7emdp
	@$(PY) tools/firmware/check_mpy.py

bench: setup ## print parser, bridge, trace, CAN, station (Plus-R and CiA 402), results-database, EtherCAT and multi-up figures (takes several minutes)
	@$(PY) tools/bench/run_benchmarks.py

docs: setup ## regenerate every document made from the code's tables (make test fails when one is stale)
	@$(PY) tools/docgen/gen_parser_doc.py
	@$(PY) tools/docgen/gen_slcan_doc.py
	@$(PY) tools/docgen/gen_cia402_doc.py
	@PYTHONPATH=firmware:tools $(PY) -m motorjig.sim.doctables --write
	@PYTHONPATH=firmware:tools $(PY) -m motorjig.capture.luagen --write

screenshots: setup ## retake the docs' pictures of the Desk and of Wireshark (needs chromium and wireshark)
	@$(PY) tools/screens/desk_screenshots.py
	@$(PY) tools/screens/desk_screenshots.py --can
	@$(PY) tools/screens/capture_screenshot.py
	@$(PY) tools/screens/capture_screenshot.py --can

sim: setup ## start the virtual bench (pty + TCP) and run the demo: make sim SIM_ARGS="--tcp-port 5000"
	@$(PY) -m motorjig.sim $(SIM_ARGS)

firmware: ## build the STM32H7_JIG image: make firmware MICROPY_DIR=/path/to/micropython
	@tools/firmware/build_firmware.sh "$(MICROPY_DIR)" "$(BUILD)" "$(BOARD_DIR)"

flash: setup ## flash the built image (DFU, st-flash or pyocd)
	@$(PY) tools/flash.py flash --build "$(BUILD)"

deploy: setup ## copy firmware/ as .mpy onto a stock MicroPython board with mpremote
	@$(PY) tools/flash.py deploy

test-qemu: setup ## run the frozen firmware on an emulated Cortex-M7: make test-qemu MICROPY_DIR=...
	@tools/firmware/test_qemu.sh "$(MICROPY_DIR)" "$(CURDIR)/build/qemu"

clean: ## remove build output and caches (keeps .venv)
	rm -rf build .pytest_cache .hypothesis
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
