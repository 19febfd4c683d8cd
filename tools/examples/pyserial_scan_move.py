"""Scan the bus and move a motor with nothing but pyserial: python pyserial_scan_move.py URL [ID]"""
import struct, sys, time, serial
def crc16(b, c=0xFFFF):
    for x in b:
        c ^= x
        for _ in range(8): c = (c >> 1) ^ 0xA001 if c & 1 else c >> 1
    return struct.pack("<H", c)
def ask(s, sid, ft, data=b""):
    body = bytes([sid, ft]) + data; s.reset_input_buffer()
    s.write(b"\xaa\xcc" + (body + crc16(body)).replace(b"\xaa", b"\xaa\xaa") + b"\xaa\xee")
    r = s.read(300).replace(b"\xaa\xaa", b"\xaa")  # waits `timeout`; reply: AA CC id type status data crc AA EE
    return r[4:] if r[2:4] == body[:2] else None
s = serial.serial_for_url(sys.argv[1], baudrate=115200, timeout=0.1); ids = [i for i in range(16) if ask(s, i, 0x01)]
print("found ids:", ids); m = int(sys.argv[2]) if len(sys.argv) > 2 else max(ids)
ask(s, m, 0x2A, b"\x01"); ask(s, m, 0x35, struct.pack("<iI", 4000, 20000)); time.sleep(0.5)
print("id %d position:" % m, struct.unpack("<i", ask(s, m, 0x51)[1:5])[0])
