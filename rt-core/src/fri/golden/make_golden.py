#!/usr/bin/env python3
"""Writes the golden FRI datagrams per version (fri-<version>.hex).

Written from the field tables (shared/docs/FRI.md, issue #25 and the published
FRIMessages schemas of KUKA's client SDKs), independently of the Rust codec:
a few lines of protobuf wire format and zlib's CRC-32. The Rust tests
(`golden_tests.rs`) compare the codec's bytes with these files; rerunning this
script must leave them unchanged.
"""
import struct
import zlib


def varint(n):
    out = b""
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out += bytes([b | 0x80])
        else:
            return out + bytes([b])


def key(tag, wt):
    return varint(tag << 3 | wt)


def vfield(tag, n):
    return key(tag, 0) + varint(n)


def lfield(tag, b):
    return key(tag, 2) + varint(len(b)) + b


def dbl(tag, x):
    return key(tag, 1) + struct.pack("<d", x)


def joints(tag, q):
    # JointValues: repeated double value = 1, unpacked (0x09 + 8 bytes LE each).
    return lfield(tag, b"".join(dbl(1, x) for x in q))


def header(mid, seq, refl):
    return lfield(1, vfield(1, mid) + vfield(2, seq) + vfield(3, refl))


MON = 0x245142
CMD = 0x34001
Q = [0.1, -0.2, 0.3, -1.4, 0.5, 0.6, -0.7]
QC = [0.11, -0.21, 0.31, -1.41, 0.51, 0.61, -0.71]
FORCE = [1.5, -2.0, 3.25, 0.125, -0.5, 0.0]


def frame(pb):
    # FRI 2.7: u32 LE length, the message, u32 LE zlib CRC-32 of the message.
    return struct.pack("<I", len(pb)) + pb + struct.pack("<I", zlib.crc32(pb) & 0xFFFFFFFF)


for v in ["1.11", "1.14", "1.15", "1.16", "2.5", "2.7"]:
    is2 = v.startswith("2")
    md = joints(1, Q)  # measuredJointPosition
    if not is2:
        md += joints(3, QC)  # commandedJointPosition: 1.x only
    if v == "2.7":
        md += lfield(6, b"".join(dbl(1, x) for x in FORCE))  # externalForce: 2.7
    mon = (
        header(MON, 7, 6)
        + lfield(2, vfield(1, 7))  # robotInfo.numberOfJoints
        + lfield(3, md)
        # connectionInfo: MONITORING_WAIT, GOOD, sendPeriod 5, receiveMultiplier 1
        + lfield(4, vfield(1, 1) + vfield(2, 2) + vfield(3, 5) + vfield(4, 1))
    )
    cmd_hdr = header(CMD, 1, 2)
    cmd_pos = header(CMD, 3, 7) + lfield(2, joints(1, Q))
    assert len(cmd_pos) == 77
    if v == "2.7":
        mon, cmd_hdr, cmd_pos = frame(mon), frame(cmd_hdr), frame(cmd_pos)
    with open(f"fri-{v}.hex", "w") as f:
        f.write(f"# FRI {v}: golden datagrams (hex), written by make_golden.py from the schema\n")
        f.write("monitoring " + mon.hex() + "\n")
        f.write("command_header_only " + cmd_hdr.hex() + "\n")
        f.write("command_position " + cmd_pos.hex() + "\n")
