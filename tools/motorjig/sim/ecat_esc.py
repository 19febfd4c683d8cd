"""An EtherCAT slave controller (ESC) as a master sees it: its registers, its RAM, and the datagrams it serves.

The part of an EtherCAT slave that is silicon (an ET1100, a LAN9252): 4 KB of registers and
process-data RAM behind them, read and written by the datagrams of every frame that passes
(``serve``). The slave's firmware is the ``app`` (``ecat_slave.EcatSlave``): the ESC tells it
what the master asked (an AL state, a mailbox written, outputs written, inputs about to be
read) and the app answers through the registers, as firmware does over the PDI.

What is modelled, with the register addresses of ETG.1000.4/.6 (``REG_*``):

* addressing: auto-increment position (APxx, ARMW: the slave whose position field is 0; every
  slave adds 1), configured station address (FPxx, FRMW: 0x0010), broadcast (Bxx), logical
  (LRD/LWR/LRW through the FMMUs 0x0600 + 16 n, byte-wise), with the working counter rules
  (read +1, write +1, read-write +3; logical read +1 and write +2 per slave);
* registers the master may write (``WRITABLE``; others keep their value), the ones the ESC
  computes (DL status with the port links, AL status, SM status, EEPROM status, system time);
* the SII EEPROM interface 0x0500-0x050F (read 8 bytes a command, write a word, reload);
* sync managers 0x0800 + 8 n: mailbox mode (written: full when the last byte is written, the
  app takes it; read: full when the app puts a reply, empty when the master reads its last
  byte, reads of an empty mailbox are not counted) and buffered mode (outputs handed to the app
  when the last byte is written, inputs taken from the app when the first is read), with the
  process-data watchdog (0x0400, 0x0420, 0x0440) triggered by writes to an SM with bit 6 set;
* distributed clocks: the local clock in ns, port receive times latched by a write to 0x0900,
  system time 0x0910 (offset 0x0920, delay 0x0928; a write compares), SYNC0 (0x0981, 0x0990, 0x09A0).
"""

import struct

# registers (ETG.1000.4)
REG_TYPE = 0x0000
REG_FMMU_COUNT = 0x0004
REG_SM_COUNT = 0x0005
REG_RAM_KB = 0x0006
REG_PORTS = 0x0007
REG_FEATURES = 0x0008
REG_STATION = 0x0010
REG_ALIAS = 0x0012
REG_DL_CONTROL = 0x0100
REG_DL_STATUS = 0x0110
REG_AL_CONTROL = 0x0120
REG_AL_STATUS = 0x0130
REG_AL_CODE = 0x0134
REG_PDI_CONTROL = 0x0140
REG_RX_ERRORS = 0x0300
REG_WD_DIVIDER = 0x0400
REG_WD_PDI = 0x0410
REG_WD_PD = 0x0420
REG_WD_STATUS = 0x0440
REG_WD_COUNT_PD = 0x0442
REG_EEP_CONFIG = 0x0500
REG_EEP_CONTROL = 0x0502
REG_EEP_ADDRESS = 0x0504
REG_EEP_DATA = 0x0508
REG_FMMU = 0x0600
REG_SM = 0x0800
REG_DC_RX_TIME = 0x0900
REG_DC_SYSTEM_TIME = 0x0910
REG_DC_RX_TIME_UNIT = 0x0918
REG_DC_OFFSET = 0x0920
REG_DC_DELAY = 0x0928
REG_DC_DIFF = 0x092C
REG_DC_ACTIVATION = 0x0981
REG_DC_SYNC0_STATUS = 0x098E
REG_DC_START = 0x0990
REG_DC_SYNC0_CYCLE = 0x09A0
RAM = 0x1000

# EEPROM control/status 0x0502
EEP_WRITE_ENABLE = 0x0001
EEP_READ8 = 0x0040
EEP_CMD_MASK = 0x0700
EEP_CMD_READ = 0x0100
EEP_CMD_WRITE = 0x0200
EEP_CMD_RELOAD = 0x0400
EEP_ERROR_CMD = 0x2000
EEP_ERROR_WRITE_ENABLE = 0x4000

# sync manager control byte
SM_MODE_MAILBOX = 0x02
SM_DIR_WRITE = 0x04  # the master writes (outputs, mailbox out); 0: the master reads
SM_WATCHDOG = 0x40
SM_STATUS_FULL = 0x08

# the register bytes a master may write (start, end exclusive); the rest keep their values
WRITABLE = ((0x0010, 0x0012), (0x0100, 0x0104), (0x0108, 0x010A), (0x0120, 0x0122), (0x0200, 0x0204),
            (0x0300, 0x0314), (0x0400, 0x0402), (0x0410, 0x0412), (0x0420, 0x0422), (0x0500, 0x0501),
            (0x0502, 0x0510), (0x0600, 0x0700), (0x0900, 0x0904), (0x0910, 0x0918), (0x0920, 0x0930),
            (0x0930, 0x0936), (0x0980, 0x0982), (0x0990, 0x0998), (0x09A0, 0x09A8))

# datagram commands (ecat.frame.CODES)
APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW, FRMW = range(1, 15)
_READS = (APRD, FPRD, BRD, LRD)
_WRITES = (APWR, FPWR, BWR, LWR)
_AUTO = (APRD, APWR, APRW, ARMW)
_FIXED = (FPRD, FPWR, FPRW, FRMW)
_BROADCAST = (BRD, BWR, BRW)
_LOGICAL = (LRD, LWR, LRW)

PORT_DELAY_NS = 500  # a frame's way through one slave and its cable, each direction


def _writable_mask(size):
    mask = bytearray(size)
    for a, b in WRITABLE:
        mask[a:b] = b"\x01" * (b - a)
    for n in range(16):  # sync managers: all but their status (5) and PDI control (7) bytes
        base = REG_SM + 8 * n
        mask[base:base + 5] = b"\x01" * 5
        mask[base + 6] = 1
    mask[RAM:] = b"\x01" * (size - RAM)
    return mask


class Esc:
    """One ESC. ``clock_ns()`` is the slave's own clock (its local time, ns); ``sii`` the EEPROM
    image; ``app`` the firmware (set by the app itself). ``position`` is set by the segment."""

    def __init__(self, clock_ns, sii, ram_kb=4, fmmus=4, sms=4, esc_type=0xC8):
        self.clock_ns = clock_ns
        self.sii = bytearray(sii)
        self.mem = bytearray(RAM + ram_kb * 1024)
        self._mask = _writable_mask(len(self.mem))
        self.fmmus = fmmus
        self.sms = sms
        self.app = None
        self.downstream = False  # another slave on port 1 (the segment sets it)
        self.hops_back = 0  # slaves after this one (port 1's round trip)
        self.position = 0
        self.link_up = True  # port 0's link: a slave with its link down sees no frame
        self.frames = 0
        self.mailbox_in_full = False
        self.mailbox_out_full = False
        self.wd_last_ns = None  # the last write to a watchdog-triggering SM
        self.outputs_seen = 0  # complete writes of the outputs SM
        m = self.mem
        m[REG_TYPE] = esc_type
        m[0x0001] = 0x01
        struct.pack_into("<H", m, 0x0002, 0x0001)
        m[REG_FMMU_COUNT] = fmmus
        m[REG_SM_COUNT] = sms
        m[REG_RAM_KB] = ram_kb
        m[REG_PORTS] = 0x0F  # ports 0 and 1: MII
        struct.pack_into("<H", m, REG_FEATURES, 0x000C)  # distributed clocks, 64 bit
        struct.pack_into("<I", m, REG_DL_CONTROL, 0x00000001)
        struct.pack_into("<H", m, REG_WD_DIVIDER, 2498)  # (2498 + 2) x 40 ns = 100 µs
        struct.pack_into("<H", m, REG_WD_PDI, 1000)
        struct.pack_into("<H", m, REG_WD_PD, 1000)  # 100 ms
        self.set_al_status(1, False, 0)
        self._eeprom_load()

    # --- what the app (the slave's firmware) uses --------------------------------------------------
    def u8(self, addr):
        return self.mem[addr]

    def u16(self, addr):
        return struct.unpack_from("<H", self.mem, addr)[0]

    def u32(self, addr):
        return struct.unpack_from("<I", self.mem, addr)[0]

    def set_al_status(self, state, error, code):
        """What the firmware says over the PDI: AL status 0x0130 (state, error bit 4) and code 0x0134."""
        struct.pack_into("<H", self.mem, REG_AL_STATUS, state | (0x10 if error else 0))
        struct.pack_into("<H", self.mem, REG_AL_CODE, code)

    @property
    def al_state(self):
        return self.mem[REG_AL_STATUS] & 0x0F

    def sm(self, n):
        """Sync manager ``n``: (start, length, control, enabled)."""
        start, length, control, _status, activate = struct.unpack_from("<HHBBB", self.mem, REG_SM + 8 * n)
        return start, length, control, bool(activate & 1)

    def post_mailbox(self, data):
        """The firmware puts a reply in the read mailbox (SM1); False while it is still full."""
        start, length, control, enabled = self.sm(1)
        if self.mailbox_out_full or not enabled or not control & SM_MODE_MAILBOX or length < len(data):
            return False
        self.mem[start:start + length] = bytes(data) + bytes(length - len(data))
        self.mailbox_out_full = True
        self.mem[REG_SM + 8 + 5] |= SM_STATUS_FULL
        return True

    def watchdog_ns(self):
        """The process-data watchdog's time in ns (0: off)."""
        return self.u16(REG_WD_PD) * (self.u16(REG_WD_DIVIDER) + 2) * 40

    def watchdog_expired(self, now_ns=None):
        """Has the process-data watchdog run out (it runs once outputs have been written)?"""
        limit = self.watchdog_ns()
        if not limit or self.wd_last_ns is None:
            return False
        now_ns = self.clock_ns() if now_ns is None else now_ns
        expired = now_ns - self.wd_last_ns > limit
        struct.pack_into("<H", self.mem, REG_WD_STATUS, 0 if expired else 1)
        return expired

    def system_time(self, local_ns=None):
        """The DC system time: local time + offset 0x0920 (64 bit)."""
        local = self.clock_ns() if local_ns is None else local_ns
        return (local + struct.unpack_from("<Q", self.mem, REG_DC_OFFSET)[0]) & 0xFFFFFFFFFFFFFFFF

    def sync0(self):
        """(start time, cycle ns) of SYNC0 when the master activated it (0x0981 bits 0 and 1), else None."""
        if self.mem[REG_DC_ACTIVATION] & 0x03 != 0x03:
            return None
        cycle = self.u32(REG_DC_SYNC0_CYCLE)
        return (struct.unpack_from("<Q", self.mem, REG_DC_START)[0], cycle) if cycle else None

    # --- a frame passing -----------------------------------------------------------------------
    def serve(self, cmd, adp, ado, data, wkc, t_ns):
        """Serve one datagram (``data``: a writable memoryview of its data, changed in place) at the
        frame's arrival ``t_ns`` on this slave's clock: (adp, wkc) as the frame leaves the slave."""
        if cmd in _AUTO:
            addressed = adp == 0
            adp = (adp + 1) & 0xFFFF
        elif cmd in _FIXED:
            addressed = adp == self.u16(REG_STATION) or (adp == self.u16(REG_ALIAS) and
                                                         self.u32(REG_DL_CONTROL) & 0x01000000)
        elif cmd in _BROADCAST:
            addressed = True
            adp = (adp + 1) & 0xFFFF
        elif cmd in _LOGICAL:
            return adp, wkc + self._logical(cmd, adp | ado << 16, data)
        else:
            return adp, wkc
        n = len(data)
        if cmd in (ARMW, FRMW):
            if addressed:
                if self._read(ado, n, data, t_ns):
                    wkc += 1
            elif self._write(ado, data, t_ns):
                wkc += 1
            return adp, wkc
        if not addressed:
            return adp, wkc
        if cmd in _READS:
            if self._read(ado, n, data, t_ns, combine=cmd == BRD):
                wkc += 1
        elif cmd in _WRITES:
            if self._write(ado, data, t_ns):
                wkc += 1
        else:  # APRW, FPRW, BRW: the data written goes in, what was there comes out
            new = bytes(data)
            if self._read(ado, n, data, t_ns, combine=cmd == BRW):
                wkc += 1
            if self._write(ado, new, t_ns):
                wkc += 2
        return adp, wkc

    def _logical(self, cmd, address, data):
        n = len(data)
        read = write = False
        out = bytes(data) if cmd == LRW else None
        maps = []
        for f in range(self.fmmus):
            start, length, _sb, _eb, phys, _pb, kind, active = struct.unpack_from("<IHBBHBBB", self.mem,
                                                                                 REG_FMMU + 16 * f)
            lo, hi = max(start, address), min(start + length, address + n)
            if active & 1 and length and lo < hi:
                maps.append((kind, phys + lo - start, lo - address, hi - address))
        # inputs go out as the firmware last left them; the outputs act after the frame has passed
        for kind, p, a, b in maps:
            if kind & 1 and cmd in (LRD, LRW) and self._read(p, b - a, data[a:b], None):
                read = True
        for kind, p, a, b in maps:
            if kind & 2 and cmd in (LWR, LRW) and self._write(p, (out if out is not None else data)[a:b], None):
                write = True
        return (1 if read else 0) + (2 if write else 0)

    # --- memory access with the ESC's rules ----------------------------------------------------------
    def _sm_overlaps(self, addr, n):
        for s in range(self.sms):
            start, length, control, enabled = self.sm(s)
            if enabled and length and start < addr + n and addr < start + length:
                yield s, start, length, control

    def _read(self, addr, n, out, t_ns, combine=False):
        m = self.mem
        if addr + n > len(m):
            return False
        if addr < RAM:
            self._refresh(addr, n)
        for s, start, length, control in self._sm_overlaps(addr, n):
            if control & SM_DIR_WRITE:
                continue
            if control & SM_MODE_MAILBOX:
                if not self.mailbox_out_full:
                    return False  # an empty mailbox: nothing read, not counted
            elif addr <= start and self.app is not None:
                self.app.fill_inputs(s, memoryview(m)[start:start + length])
        if combine:
            for i in range(n):
                out[i] |= m[addr + i]
        else:
            out[:] = m[addr:addr + n]
        for s, start, length, control in self._sm_overlaps(addr, n):
            if not control & SM_DIR_WRITE and control & SM_MODE_MAILBOX and addr + n >= start + length:
                self.mailbox_out_full = False
                m[REG_SM + 8 * s + 5] &= ~SM_STATUS_FULL & 0xFF
                if self.app is not None:
                    self.app.mailbox_read()
        return True

    def _write(self, addr, data, t_ns):
        m = self.mem
        n = len(data)
        if addr + n > len(m):
            return False
        sms = list(self._sm_overlaps(addr, n)) if addr + n > RAM else []
        for s, start, length, control in sms:
            if not control & SM_DIR_WRITE:
                return False  # the master cannot write what the slave sends
            if control & SM_MODE_MAILBOX and self.mailbox_in_full:
                return False  # the firmware has not taken the last one yet
        if addr >= RAM:
            m[addr:addr + n] = data
        else:
            mask = self._mask
            for i in range(n):
                if mask[addr + i]:
                    m[addr + i] = data[i]
            self._written(addr, n, t_ns)
        for s, start, length, control in sms:
            if control & SM_WATCHDOG:
                self.wd_last_ns = self.clock_ns()
                struct.pack_into("<H", m, REG_WD_STATUS, 1)
            if addr + n < start + length:
                continue  # complete when the buffer's last byte is written
            if control & SM_MODE_MAILBOX:
                self.mailbox_in_full = True
                m[REG_SM + 8 * s + 5] |= SM_STATUS_FULL
                payload = bytes(m[start:start + length])
                self.mailbox_in_full = False  # the firmware reads it at once
                m[REG_SM + 8 * s + 5] &= ~SM_STATUS_FULL & 0xFF
                if self.app is not None:
                    self.app.mailbox_written(payload)
            else:
                self.outputs_seen += 1
                if self.app is not None:
                    self.app.outputs_written(s, bytes(m[start:start + length]))
        return True

    def _refresh(self, addr, n):
        """Bring the registers the ESC computes up to date before a read of [addr, addr + n)."""
        end = addr + n
        m = self.mem
        if addr < REG_DL_STATUS + 2 and end > REG_DL_STATUS:
            status = 0x0001 | 0x0010 | 0x0200  # PDI operational, port 0 link and communication
            status |= 0x0020 | 0x0800 if self.downstream else 0x0400  # port 1: open and talking, else closed
            struct.pack_into("<H", m, REG_DL_STATUS, status)
        if addr < REG_EEP_CONTROL + 2 and end > REG_EEP_CONTROL:
            m[REG_EEP_CONTROL] |= EEP_READ8
        if addr < REG_DC_SYSTEM_TIME + 8 and end > REG_DC_SYSTEM_TIME:
            struct.pack_into("<Q", m, REG_DC_SYSTEM_TIME, self.system_time())
        if addr < REG_WD_STATUS + 2 and end > REG_WD_STATUS:
            self.watchdog_expired()

    def _written(self, addr, n, t_ns):
        """What a write to the registers [addr, addr + n) starts."""
        end = addr + n
        m = self.mem
        if addr < REG_AL_CONTROL + 2 and end > REG_AL_CONTROL and self.app is not None:
            self.app.al_control(self.u16(REG_AL_CONTROL))
        if addr < REG_EEP_CONTROL + 2 and end > REG_EEP_CONTROL:
            self._eeprom_command()
        if addr <= REG_DC_RX_TIME < end:
            self._latch(t_ns)
        if addr < REG_DC_SYSTEM_TIME + 8 and end > REG_DC_SYSTEM_TIME:
            written = struct.unpack_from("<Q", m, REG_DC_SYSTEM_TIME)[0]
            diff = (written - self.system_time()) & 0xFFFFFFFF
            struct.pack_into("<I", m, REG_DC_DIFF, diff)
        if addr < REG_RX_ERRORS + 0x14 and end > REG_RX_ERRORS:
            m[REG_RX_ERRORS:REG_RX_ERRORS + 0x14] = bytes(0x14)  # a write clears the counters

    def _latch(self, t_ns):
        """A write to 0x0900: each port's receive time of this frame, on the local clock."""
        t = self.clock_ns() if t_ns is None else t_ns
        port0 = t
        port1 = t + 2 * PORT_DELAY_NS * (self.hops_back + 1) if self.downstream else t
        struct.pack_into("<IIII", self.mem, REG_DC_RX_TIME, port0 & 0xFFFFFFFF, port1 & 0xFFFFFFFF,
                         port0 & 0xFFFFFFFF, port0 & 0xFFFFFFFF)
        struct.pack_into("<Q", self.mem, REG_DC_RX_TIME_UNIT, port0 & 0xFFFFFFFFFFFFFFFF)

    # --- the SII EEPROM interface ------------------------------------------------------------------
    def _eeprom_load(self):
        """Power-up and reload: the alias and the PDI control come from the EEPROM."""
        struct.pack_into("<H", self.mem, REG_ALIAS, struct.unpack_from("<H", self.sii, 0x04 * 2)[0])
        self.mem[REG_PDI_CONTROL] = self.sii[0]

    def _eeprom_command(self):
        m = self.mem
        control = self.u16(REG_EEP_CONTROL)
        cmd = control & EEP_CMD_MASK
        status = EEP_READ8
        word = self.u32(REG_EEP_ADDRESS)
        if cmd == EEP_CMD_READ:
            data = bytes(self.sii[word * 2:word * 2 + 8]).ljust(8, b"\xff")
            m[REG_EEP_DATA:REG_EEP_DATA + 8] = data
        elif cmd == EEP_CMD_WRITE:
            if not control & EEP_WRITE_ENABLE:
                status |= EEP_ERROR_WRITE_ENABLE
            elif word * 2 + 2 <= len(self.sii):
                self.sii[word * 2:word * 2 + 2] = m[REG_EEP_DATA:REG_EEP_DATA + 2]
            else:
                status |= EEP_ERROR_CMD
        elif cmd == EEP_CMD_RELOAD:
            self._eeprom_load()
        elif cmd:
            status |= EEP_ERROR_CMD
        struct.pack_into("<H", m, REG_EEP_CONTROL, status)  # done at once: never busy
