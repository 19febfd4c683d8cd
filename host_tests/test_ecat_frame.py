"""EtherCAT frames (motorjig.ecat.frame): what a master sends and slaves answer, byte for byte.

Built frames parse back to the same datagrams (hypothesis), a frame from the specification's
layout decodes to its fields, anything that is not a whole EtherCAT frame is refused in one
sentence, and Wireshark's own EtherCAT dissector (tshark) reads our frames field for field.
"""

import shutil
import struct
import subprocess

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorjig.ecat import frame as E

datagrams = st.builds(
    lambda cmd, idx, adp, ado, data, wkc, circ: E.Datagram(cmd, adp, ado, data, idx, wkc, 0, circ),
    st.sampled_from(sorted(E.COMMANDS)), st.integers(0, 255), st.integers(0, 0xFFFF), st.integers(0, 0xFFFF),
    st.binary(max_size=64), st.integers(0, 0xFFFF), st.booleans())


@given(st.lists(datagrams, min_size=1, max_size=8))
def test_a_built_frame_parses_back_to_its_datagrams(ds):
    got = E.parse(E.build(ds))
    assert [(d.cmd, d.idx, d.adp, d.ado, bytes(d.data), d.wkc, d.circulating) for d in got] == \
        [(d.cmd, d.idx, d.adp, d.ado, bytes(d.data), d.wkc, d.circulating) for d in ds]


def test_the_layout_of_a_broadcast_read_counting_slaves():
    """BRD of register 0x0000, 2 bytes, answered by 3 slaves (wkc 3): the bytes as the spec lays them."""
    frame = bytes.fromhex("ffffffffffff" "020000000001" "88a4" "0e10" "07" "05" "0000" "0000" "0200" "0000"
                          "1100" "0300") + bytes(32)
    (d,) = E.parse(frame)
    assert (d.name, d.idx, d.adp, d.ado, bytes(d.data), d.wkc) == ("BRD", 5, 0, 0, b"\x11\x00", 3)
    assert E.build([d])[:len(frame) - 32] == frame[:len(frame) - 32]


def test_a_logical_datagram_carries_one_32_bit_address():
    d = E.Datagram("LRW", logical=0x00012345, data=b"\x01\x02")
    (got,) = E.parse(E.build([d]))
    assert got.logical == 0x00012345 and got.name == "LRW"


@pytest.mark.parametrize("frame,words", [
    (b"\x00" * 10, "too short"),
    (bytes(12) + b"\x08\x00" + bytes(46), "ethertype 0x0800 is not EtherCAT"),
    (bytes(12) + b"\x88\xa4" + struct.pack("<H", 12 | 5 << 12) + bytes(44), "type 5 carries no datagrams"),
    (bytes(12) + b"\x88\xa4" + struct.pack("<H", 500 | 1 << 12) + bytes(44), "announces 500 bytes"),
    (bytes(12) + b"\x88\xa4" + struct.pack("<H", 14 | 1 << 12) + struct.pack("<BBHHHH", 1, 0, 0, 0, 40, 0)
     + bytes(44), "announces 40 bytes of data"),
    (bytes(12) + b"\x88\xa4" + struct.pack("<H", 12 | 1 << 12) + struct.pack("<BBHHHH", 99, 0, 0, 0, 0, 0)
     + bytes(34), "command 99"),
])
def test_what_is_not_a_whole_etherCAT_frame_is_refused_in_one_sentence(frame, words):
    with pytest.raises(ValueError, match=words):
        E.parse(frame)


def test_build_refuses_what_no_frame_can_carry():
    with pytest.raises(ValueError, match="at least one datagram"):
        E.build([])
    with pytest.raises(ValueError, match="at most 2047"):
        E.Datagram("LWR", data=bytes(3000))
    with pytest.raises(ValueError, match="command 15"):
        E.Datagram(15)


def test_wiresharks_dissector_reads_our_frames(tmp_path):
    if shutil.which("tshark") is None:
        pytest.skip("tshark is not installed (the setup installs it under CI)")
    frame = E.build([E.Datagram("BRD", 0, 0x0130, b"\x00\x00", idx=3, wkc=2),
                     E.Datagram("LRW", logical=0x10000, data=b"\x01\x02\x03", wkc=6)])
    pcap = tmp_path / "ecat.pcap"
    pcap.write_bytes(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)
                     + struct.pack("<IIII", 1, 0, len(frame), len(frame)) + frame)
    out = subprocess.run(["tshark", "-r", str(pcap), "-T", "fields", "-e", "ecat.cmd", "-e", "ecat.idx",
                          "-e", "ecat.ado", "-e", "ecat.cnt", "-e", "ecat.lad", "-E", "separator=;"],
                         capture_output=True, text=True, timeout=60).stdout.strip()
    assert out == "0x07,0x0c;0x03,0x00;0x0130;2,6;0x00010000", out
