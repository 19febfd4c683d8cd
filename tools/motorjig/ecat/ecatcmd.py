"""``jigctl ecat``: an EtherCAT line from this PC's network interface, through SOEM (pysoem).

    jigctl ecat scan  --ifname IF                 the slaves: position, name, identity, AL state
    jigctl ecat state --ifname IF [--set STATE]   their AL states and status codes; request one for all
    jigctl ecat sdo read  --ifname IF POS INDEX[:SUB]
    jigctl ecat sdo write --ifname IF POS INDEX[:SUB] VALUE
    jigctl ecat pdo   --ifname IF POS             the PDO assignment 0x1C12/0x1C13 and each mapping
    jigctl ecat dump  --ifname IF POS             the slave's SII EEPROM: fixed fields and categories

Objects are typed from an EDS (``--eds``; default: the bench's servo's, the project's CiA 402 EDS).
Every command needs root (raw sockets), as every EtherCAT master does; errors are one sentence.
"""

import os
import struct

from motorjig.commands import EXIT_OK, UsageError
from motorjig.ecat import sii

STATES = {"init": 1, "preop": 2, "safeop": 4, "op": 8}
STATE_NAMES = {1: "INIT", 2: "PRE-OP", 3: "BOOT", 4: "SAFE-OP", 8: "OP"}


def add_ecat_arguments(sp):
    sub = sp.add_subparsers(dest="ecat_command", metavar="ECAT_COMMAND")
    sub.required = True

    def add(name, fn, help_text, parent=sub):
        p = parent.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--ifname", required=True, metavar="IF",
                       help="this PC's network interface on the EtherCAT line (the bench prints its own: mjmN)")
        p.add_argument("--eds", metavar="FILE", help="the EDS that types the objects (default: the project's CiA 402 "
                                                     "EDS, the bench servo's)")
        p.set_defaults(ecat_fn=fn)
        return p

    add("scan", cmd_scan, "the slaves on the line: position, name, identity, AL state")
    p = add("state", cmd_state, "the slaves' AL states and status codes; --set requests one for every slave")
    p.add_argument("--set", choices=tuple(STATES), help="the state to request (init, preop, safeop, op)")
    p = sub.add_parser("sdo", help="read or write an object by CoE SDO", description="read or write an object by "
                                                                                  "CoE SDO")
    ssub = p.add_subparsers(dest="sdo_action", metavar="ACTION")
    ssub.required = True
    r = add("read", cmd_sdo_read, "read an object (typed from the EDS; raw bytes when it is not in it)", ssub)
    r.add_argument("position", type=int, help="the slave's position on the line, from 0")
    r.add_argument("object", metavar="INDEX[:SUB]", help="e.g. 0x6041, 0x1018:1")
    w = add("write", cmd_sdo_write, "write an object (typed from the EDS)", ssub)
    w.add_argument("position", type=int, help="the slave's position on the line, from 0")
    w.add_argument("object", metavar="INDEX[:SUB]", help="e.g. 0x6081")
    w.add_argument("value", help="the value (a number, 0x hex)")
    p = add("pdo", cmd_pdo, "the PDO assignment (0x1C12, 0x1C13) and each PDO's mapping, read by SDO")
    p.add_argument("position", type=int, help="the slave's position on the line, from 0")
    p = add("dump", cmd_dump, "the slave's SII EEPROM: identity, mailbox, name, categories")
    p.add_argument("position", type=int, help="the slave's position on the line, from 0")


def cmd_ecat(args):
    return args.ecat_fn(args)


def _object(text):
    index, _, sub = text.partition(":")
    try:
        return int(index, 0), int(sub, 0) if sub else 0
    except ValueError:
        raise UsageError("%r is not INDEX[:SUB] (e.g. 0x6041 or 0x1018:1)" % text) from None


def _master(args):
    """An open pysoem master with the line scanned (UsageError: one sentence)."""
    if not os.path.exists(os.path.join("/sys/class/net", args.ifname)):
        raise UsageError("no network interface named %s (`ip link` lists them; the bench prints its own)"
                         % args.ifname)
    if os.geteuid() != 0:
        raise UsageError("an EtherCAT master opens raw sockets: run jigctl ecat as root (sudo)")
    try:
        import pysoem
    except ImportError:
        raise UsageError("jigctl ecat needs pysoem: pip install 'motorjig[ecat]'") from None
    m = pysoem.Master()
    try:
        m.open(args.ifname)
    except Exception as exc:
        raise UsageError("cannot open %s: %s" % (args.ifname, exc)) from None
    if m.config_init() <= 0:
        m.close()
        raise UsageError("no EtherCAT slave answered on %s" % args.ifname)
    return m


def _slave(m, position):
    if not 0 <= position < len(m.slaves):
        raise UsageError("slave position %d is not on the line (%d slave%s: 0..%d)" % (
            position, len(m.slaves), "" if len(m.slaves) == 1 else "s", len(m.slaves) - 1))
    return m.slaves[position]


def _od(args):
    from motorjig.can import EDS_PATH
    from motorjig.can import objects as O

    return O.load_eds(args.eds or EDS_PATH)


def _var(od, index, sub):
    obj = od.get(index) if hasattr(od, "get") else None
    if obj is None:
        return None
    try:
        return obj[sub] if hasattr(obj, "subindices") else obj
    except KeyError:
        return None


def _al_text(code):
    import pysoem

    return "0x%04X %s" % (code, pysoem.al_status_code_to_string(code))


def cmd_scan(args):
    m = _master(args)
    try:
        m.read_state()
        print("%-4s %-28s %-10s %-10s %-10s %s" % ("pos", "name", "vendor", "product", "revision", "state"))
        for i, s in enumerate(m.slaves):
            state = STATE_NAMES.get(s.state & 0x0F, "0x%02X" % s.state)
            error = " (error: AL status %s)" % _al_text(s.al_status) if s.state & 0x10 else ""
            print("%-4d %-28s 0x%08X 0x%08X 0x%08X %s%s" % (i, s.name, s.man, s.id, s.rev, state, error))
    finally:
        m.close()
    return EXIT_OK


def cmd_state(args):
    m = _master(args)
    try:
        if args.set:
            m.state = STATES[args.set]
            m.write_state()
            m.state_check(STATES[args.set], 50000)
        m.read_state()
        for i, s in enumerate(m.slaves):
            print("%d %s: %s, AL status %s" % (i, s.name, STATE_NAMES.get(s.state & 0x0F, "0x%02X" % s.state),
                                               _al_text(s.al_status)))
        if args.set and any(s.state != STATES[args.set] for s in m.slaves):
            print("jigctl: note: not every slave reached %s (OP needs a master's cycle: the station runs one, this "
                  "command does not)" % args.set.upper())
    finally:
        m.close()
    return EXIT_OK


def _sdo_error(exc, what):
    from motorjig.can import cia301

    code = getattr(exc, "abort_code", None)
    if code is not None:
        return UsageError("%s: abort %s" % (what, cia301.abort_text(code)))
    return UsageError("%s: no answer (%s)" % (what, type(exc).__name__))


def cmd_sdo_read(args):
    index, sub = _object(args.object)
    od = _od(args)
    m = _master(args)
    try:
        s = _slave(m, args.position)
        try:
            raw = s.sdo_read(index, sub)
        except Exception as exc:
            raise _sdo_error(exc, "slave %d refused the read of 0x%04X:%02X" % (args.position, index, sub)) from None
        var = _var(od, index, sub)
        value = var.decode_raw(raw) if var is not None else None
        name = " %s" % var.name if var is not None else ""
        shown = ("0x%X (%d)" % (value, value) if isinstance(value, int) else repr(value)) if var is not None \
            else raw.hex(" ")
        print("0x%04X:%02X%s = %s" % (index, sub, name, shown))
    finally:
        m.close()
    return EXIT_OK


def cmd_sdo_write(args):
    index, sub = _object(args.object)
    var = _var(_od(args), index, sub)
    if var is None:
        raise UsageError("0x%04X:%02X is not in the EDS: its type is unknown (--eds)" % (index, sub))
    try:
        value = int(args.value, 0) if var.data_type != 0x9 else args.value
        data = var.encode_raw(value)
    except (ValueError, struct.error) as exc:
        raise UsageError("%r is no value for 0x%04X:%02X %s: %s" % (args.value, index, sub, var.name, exc)) from None
    m = _master(args)
    try:
        s = _slave(m, args.position)
        try:
            s.sdo_write(index, sub, data)
        except Exception as exc:
            raise _sdo_error(exc, "slave %d refused the write of 0x%04X:%02X" % (args.position, index, sub)) from None
        print("0x%04X:%02X %s = %s written" % (index, sub, var.name, args.value))
    finally:
        m.close()
    return EXIT_OK


def cmd_pdo(args):
    m = _master(args)
    try:
        s = _slave(m, args.position)

        def u(index, sub, size):
            return int.from_bytes(s.sdo_read(index, sub)[:size], "little")

        try:
            for assign, what in ((0x1C12, "RxPDO (outputs)"), (0x1C13, "TxPDO (inputs)")):
                pdos = [u(assign, i, 2) for i in range(1, u(assign, 0, 1) + 1)]
                print("0x%04X %s: %s" % (assign, what, ", ".join("0x%04X" % p for p in pdos) or "none"))
                for pdo in pdos:
                    for j in range(1, u(pdo, 0, 1) + 1):
                        e = u(pdo, j, 4)
                        print("  0x%04X:%d  0x%04X:%02X  %d bits" % (pdo, j, e >> 16, e >> 8 & 0xFF, e & 0xFF))
        except Exception as exc:
            raise _sdo_error(exc, "slave %d's PDO objects" % args.position) from None
    finally:
        m.close()
    return EXIT_OK


def cmd_dump(args):
    m = _master(args)
    try:
        s = _slave(m, args.position)
        data = bytearray()
        for word in range(0, 1024, 2):
            data += bytes(s.eeprom_read(word))
            if len(data) >= 0x84 and b"\xff\xff" in data[0x80:] and _ended(data):
                break
    finally:
        m.close()
    f = sii.fields(bytes(data))
    print("vendor 0x%08X product 0x%08X revision 0x%08X serial 0x%08X alias %d (checksum %s)" % (
        f["vendor_id"], f["product_code"], f["revision"], f["serial"], f["alias"],
        "ok" if f["checksum_ok"] else "WRONG"))
    print("mailbox: out 0x%04X (%d bytes), in 0x%04X (%d bytes), protocols 0x%02X" % (
        f["rx_offset"], f["rx_size"], f["tx_offset"], f["tx_size"], f["mailbox_protocols"]))
    print("name: %s" % (sii.device_name(bytes(data)) or "-"))
    try:
        for kind, raw in sii.categories(bytes(data)):
            print("category %s (%d): %d bytes" % (sii.CATEGORY_NAMES.get(kind, "?"), kind, len(raw)))
    except ValueError as exc:
        print("jigctl: note: %s" % exc)
    return EXIT_OK


def _ended(data):
    try:
        sii.categories(bytes(data))
        return True
    except ValueError:
        return False
