"""CoE (CANopen over EtherCAT, ETG.1000.6) server of a simulated slave: SDOs and emergencies in the mailbox.

A CoE message is a 2-byte header (bits 0-8 a number, bits 12-15 the service) and its data.
The SDO service carries CiA 301's SDO command byte, index and sub-index, then, unlike CAN,
a whole object in one message when it fits: an expedited transfer (up to 4 bytes), a normal
one (the size, then the data), and segments only for what the mailbox cannot hold. Aborts
carry CiA 301's codes. ``SdoServer.request(body)`` answers one message with the replies (a
list of CoE bodies) on an object store with ``upload(index, sub)`` and ``download(index, sub,
data)`` (``drive402.Drive402``); ``emergency(code, register)`` makes an EMCY message.
"""

import struct

SERVICE_EMERGENCY, SERVICE_SDO_REQUEST, SERVICE_SDO_RESPONSE, SERVICE_SDO_INFO = 1, 2, 3, 8
SDO_HEADER = 2 + 8  # CoE header + command, index, sub-index, 4 bytes
ABORT_TOGGLE = 0x05030000
ABORT_COMMAND = 0x05040001
ABORT_UNSUPPORTED = 0x06010000
ABORT_LENGTH = 0x06070010
ABORT_GENERAL = 0x08000000


def _coe(service, payload):
    return struct.pack("<H", service << 12) + payload


def _sdo(payload):
    return _coe(SERVICE_SDO_RESPONSE, payload)


def abort(index, sub, code):
    """An SDO abort transfer message: sent as an SDO *request* (ETG.1000.6), whichever side aborts."""
    return _coe(SERVICE_SDO_REQUEST, struct.pack("<BHBI", 0x80, index, sub, code))


def emergency(code, register, data=b""):
    """A CoE emergency: error code, error register, 5 bytes of data."""
    return _coe(SERVICE_EMERGENCY, struct.pack("<HB", code, register) + bytes(data)[:5].ljust(5, b"\x00"))


class SdoServer:
    """The SDO side of CoE for ``store`` with a mailbox of ``mailbox_size`` bytes (its 6-byte header
    included). ``abort_code``/``abort_scope``: the bench's sdo-abort fault (every request, or one
    object's, answered with that code)."""

    def __init__(self, store, mailbox_size):
        self.store = store
        self.room = mailbox_size - 6 - SDO_HEADER  # the data a normal transfer's first message holds
        self.segment_room = mailbox_size - 6 - 3  # CoE header + the segment's command byte
        self.abort_code = None
        self.abort_scope = None
        self.requests = 0
        self._up = None  # an upload in segments: [index, sub, data, position, toggle]
        self._down = None  # a download in segments: [index, sub, size, data, toggle]

    def request(self, body):
        """The replies (CoE bodies) to one CoE message from the master."""
        if len(body) < 2:
            return []
        service = struct.unpack_from("<H", body, 0)[0] >> 12
        if service != SERVICE_SDO_REQUEST:
            return []  # no PDOs in the mailbox, no SDO information: not answered
        d = bytes(body[2:]).ljust(8, b"\x00")
        self.requests += 1
        cmd = d[0]
        ccs = cmd >> 5
        index, sub = struct.unpack_from("<HB", d, 1)
        if ccs == 4:  # the master aborts
            self._up = self._down = None
            return []
        if ccs in (1, 2) and self._aborted(index, sub):
            self._up = self._down = None
            return [abort(index, sub, self.abort_code)]
        if cmd & 0x10 and ccs in (1, 2):
            return [abort(index, sub, ABORT_UNSUPPORTED)]  # complete access is not offered (SII)
        if ccs == 2:
            return [self._upload(index, sub)]
        if ccs == 1:
            return [self._download(cmd, index, sub, d, bytes(body[2:]))]
        if ccs == 3:
            return [self._upload_segment(cmd)]
        if ccs == 0:
            return [self._download_segment(cmd, bytes(body[2:]))]
        return [abort(index, sub, ABORT_COMMAND)]

    def _aborted(self, index, sub):
        if self.abort_code is None:
            return False
        scope = self.abort_scope
        return scope is None or (index == scope[0] and scope[1] in (None, sub))

    def _upload(self, index, sub):
        self._up = None
        data, code = self.store.upload(index, sub)
        if data is None:
            return abort(index, sub, code)
        if len(data) <= 4:
            n = 4 - len(data)
            return _sdo(bytes([0x43 | n << 2]) + struct.pack("<HB", index, sub) + data + bytes(n))
        first = data[:self.room]
        if len(data) > self.room:
            self._up = [index, sub, data, len(first), 0]
        return _sdo(struct.pack("<BHBI", 0x41, index, sub, len(data)) + first)

    def _upload_segment(self, cmd):
        x = self._up
        if x is None:
            return abort(0, 0, ABORT_COMMAND)
        index, sub, data, pos, toggle = x
        if (cmd >> 4 & 1) != toggle:
            self._up = None
            return abort(index, sub, ABORT_TOGGLE)
        chunk = data[pos:pos + self.segment_room]
        x[3] = pos + len(chunk)
        last = x[3] >= len(data)
        x[4] ^= 1
        if last:
            self._up = None
        n = max(0, 7 - len(chunk))
        return _sdo(bytes([toggle << 4 | n << 1 | (1 if last else 0)]) + chunk + bytes(n))

    def _download(self, cmd, index, sub, d, raw):
        self._down = None
        expedited, sized = cmd >> 1 & 1, cmd & 1
        if expedited:
            data = d[4:8 - (cmd >> 2 & 3)] if sized else d[4:8]
            code = self._download_value(index, sub, data, sized)
        else:
            size = struct.unpack_from("<I", d, 4)[0]
            data = raw[8:8 + size]
            if len(data) < size:
                self._down = [index, sub, size, data, 0]
                return _sdo(struct.pack("<BHBI", 0x60, index, sub, 0))
            code = self.store.download(index, sub, data)
        if code:
            return abort(index, sub, code)
        return _sdo(struct.pack("<BHBI", 0x60, index, sub, 0))

    def _download_value(self, index, sub, data, sized):
        code = self.store.download(index, sub, data)
        if code == ABORT_LENGTH and not sized:  # 4 bytes without a size: the object's own size counts
            for n in (1, 2):
                if not self.store.download(index, sub, data[:n]):
                    return 0
        return code

    def _download_segment(self, cmd, raw):
        x = self._down
        if x is None:
            return abort(0, 0, ABORT_COMMAND)
        index, sub, size, data, toggle = x
        if (cmd >> 4 & 1) != toggle:
            self._down = None
            return abort(index, sub, ABORT_TOGGLE)
        chunk = raw[1:]
        if len(chunk) <= 7:
            chunk = chunk[:7 - (cmd >> 1 & 7)]
        x[3] = data = data + chunk
        x[4] ^= 1
        reply = _sdo(bytes([0x20 | toggle << 4]) + bytes(7))
        if not cmd & 1:
            return reply
        self._down = None
        code = self.store.download(index, sub, data[:size]) if len(data) >= size else ABORT_LENGTH
        return abort(index, sub, code) if code else reply
