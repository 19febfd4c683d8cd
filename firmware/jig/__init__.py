"""MotorJig firmware: an RS-485 bridge between a PC bus master and FASTECH Plus-R drives.

Every module here imports under MicroPython (the board image) and under CPython
(host tests, virtual bench, PC tools). Only ``board`` touches hardware.
"""
