"""The Net F/T RDT codec on bytes: requests, records, scaling, sequence tracking; fuzzed with hypothesis."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinstretch.drivers.forcesensor.netft import (
    RECORD_SIZE,
    RdtCommand,
    RdtRecord,
    SequenceTracker,
    counts_to_ft,
    decode_record,
    decode_records,
    decode_request,
    encode_record,
    encode_request,
    ft_to_counts,
    parse_calibration,
)
from skinstretch.drivers.errors import ProtocolError
from skinstretch.processing.errors import InvalidInputError


def test_request_bytes_match_the_ati_layout():
    assert encode_request(RdtCommand.START_REALTIME) == bytes.fromhex("1234 0002 00000000")
    assert encode_request(RdtCommand.SET_SOFTWARE_BIAS) == bytes.fromhex("1234 0042 00000000")
    assert encode_request(RdtCommand.START_BUFFERED, sample_count=10) == bytes.fromhex("1234 0003 0000000a")
    assert decode_request(bytes.fromhex("1234 0000 00000005")) == (RdtCommand.STOP, 5)


def test_bad_requests():
    with pytest.raises(ProtocolError, match="header"):
        decode_request(bytes.fromhex("4321 0002 00000000"))
    with pytest.raises(ProtocolError, match="unknown RDT command"):
        decode_request(bytes.fromhex("1234 0007 00000000"))
    with pytest.raises(ProtocolError, match="8 bytes"):
        decode_request(b"\x12\x34")
    with pytest.raises(InvalidInputError, match="command"):
        encode_request(9)
    with pytest.raises(InvalidInputError, match="sample_count"):
        encode_request(RdtCommand.STOP, sample_count=-1)


def test_record_round_trip_and_layout():
    rec = RdtRecord(7, 123456, 0, (1_000_000, -2_000_000, 3, -4, 5, -(2**31)))
    data = encode_record(rec)
    assert len(data) == RECORD_SIZE == 36
    assert data == struct.pack(">III6i", 7, 123456, 0, 1_000_000, -2_000_000, 3, -4, 5, -(2**31))
    assert decode_record(data) == rec
    assert decode_records(data * 3) == [rec] * 3  # buffered mode: several records per datagram
    with pytest.raises(ProtocolError, match="multiple of 36"):
        decode_records(data + b"\x00")
    with pytest.raises(ProtocolError):
        decode_records(b"")
    with pytest.raises(InvalidInputError, match="32-bit"):
        encode_record(RdtRecord(1, 1, 0, (2**31, 0, 0, 0, 0, 0)))


def test_counts_scale_to_newtons_and_back():
    ft = counts_to_ft((1_000_000, -500_000, 2_500_000, 1000, 0, -1000), counts_per_force=1e6, counts_per_torque=1e3)
    np.testing.assert_allclose(ft, [1.0, -0.5, 2.5, 1.0, 0.0, -1.0])
    counts = ft_to_counts(ft, counts_per_force=1e6, counts_per_torque=1e3)
    assert counts == (1_000_000, -500_000, 2_500_000, 1000, 0, -1000)
    assert ft_to_counts([1e9, 0, 0, 0, 0, 0], counts_per_force=1e6, counts_per_torque=1e6)[0] == 2**31 - 1
    with pytest.raises(InvalidInputError, match="6 finite"):
        ft_to_counts([np.nan] * 6, counts_per_force=1, counts_per_torque=1)


def test_sequence_tracker_counts_gaps_late_and_duplicates():
    t = SequenceTracker()
    verdicts = [t.feed(s)[0] for s in (1, 2, 5, 3, 3, 6, 6)]
    assert verdicts == ["accept", "accept", "accept", "late", "duplicate", "accept", "duplicate"]
    assert (t.lost, t.reordered, t.duplicates) == (1, 1, 2)  # 4 never came; 3 came late


def test_sequence_tracker_unwraps_32_bits():
    t = SequenceTracker()
    out = [t.feed(s)[1] for s in (2**32 - 2, 2**32 - 1, 0, 2)]
    assert out == [2**32 - 2, 2**32 - 1, 2**32, 2**32 + 2]
    assert t.lost == 1
    assert t.feed(1) == ("late", 2**32 + 1) and t.lost == 0


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_fuzzed_datagrams_decode_or_raise_protocol_error(data):
    try:
        records = decode_records(data)
    except ProtocolError:
        assert len(data) == 0 or len(data) % RECORD_SIZE
        return
    assert len(records) * RECORD_SIZE == len(data)
    assert b"".join(encode_record(r) for r in records) == data


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=20))
def test_fuzzed_requests_decode_or_raise_protocol_error(data):
    try:
        command, count = decode_request(data)
    except ProtocolError:
        return
    assert encode_request(command, sample_count=count) == data


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, 40), max_size=60))
def test_tracker_never_loses_count(sequence_steps):
    """Whatever the arrival order, accepted + late + duplicates equals what was fed."""
    t = SequenceTracker()
    seqs = np.cumsum([1] + sequence_steps) % 50  # wraps and repeats on purpose
    verdicts = [t.feed(int(s))[0] for s in seqs]
    assert verdicts.count("duplicate") == t.duplicates
    assert verdicts.count("late") == t.reordered
    assert t.lost >= 0


NETFTAPI2 = b"""<?xml version="1.0"?>
<netft><setserial>FT12345</setserial><cfgcpf>1000000</cfgcpf><cfgcpt>1000</cfgcpt><scfgfu>2</scfgfu></netft>"""


def test_calibration_is_read_from_netftapi2_xml():
    assert parse_calibration(NETFTAPI2) == (1_000_000.0, 1000.0)
    with pytest.raises(ProtocolError, match="cfgcpt"):
        parse_calibration(b"<netft><cfgcpf>1000000</cfgcpf></netft>")
    with pytest.raises(ProtocolError, match="cfgcpf"):
        parse_calibration(b"<netft><cfgcpf>-3</cfgcpf><cfgcpt>1</cfgcpt></netft>")
    with pytest.raises(ProtocolError, match="well-formed"):
        parse_calibration(b"<netft><cfgcpf>")
