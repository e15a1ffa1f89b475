"""The STReSS wire codec: framing, CRC, payloads, and a decoder that survives any byte stream."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.drivers.errors import ProtocolError
from skinstretch.processing.errors import InvalidInputError


def test_crc_is_ccitt_false_check_value():
    assert sp.crc16_ccitt(b"123456789") == 0x29B1


def test_packet_layout_is_byte_exact():
    packet = sp.encode_packet(seq=7, command=sp.Command.IDENTIFY)
    assert packet == bytes.fromhex("a55a000701452a")
    frame = sp.encode_packet(seq=255, command=sp.Command.FRAME, payload=bytes(100))
    assert len(frame) == sp.OVERHEAD + 100 == 107
    assert frame[:5] == bytes([0xA5, 0x5A, 100, 255, 0x06])
    assert int.from_bytes(frame[-2:], "big") == sp.crc16_ccitt(frame[2:-2])


@pytest.mark.parametrize("kwargs", [dict(seq=256, command=1), dict(seq=-1, command=1), dict(seq=0, command=300),
                                    dict(seq=0, command=1, payload=bytes(256))])
def test_encode_rejects_bad_fields(kwargs):
    with pytest.raises(InvalidInputError):
        sp.encode_packet(**kwargs)


def test_positions_round_trip_on_the_half_micron_grid(rng):
    positions = np.round(rng.uniform(-50, 50, (10, 10)) * 2) / 2
    assert np.array_equal(sp.decode_positions(sp.encode_positions(positions)), positions)
    assert sp.encode_positions(np.full((10, 10), 50.0))[0] == 100


@pytest.mark.parametrize("bad", [np.full((10, 10), np.nan), np.full((10, 10), 64.0), np.zeros((9, 10))])
def test_encode_positions_refuses_unsafe_or_misshapen(bad):
    with pytest.raises(InvalidInputError):
        sp.encode_positions(bad)


def test_payload_codecs_round_trip(rng):
    ident = sp.Identity(1, 10, 10, 50.0, 700, "stresssim 1.0")
    assert sp.Identity.decode(ident.encode()) == ident
    cfg = sp.WatchdogConfig(watchdog_s=0.05, max_step_um=7.5)
    assert sp.WatchdogConfig.decode(cfg.encode()) == cfg
    measured = np.round(rng.uniform(-60, 60, (10, 10)) * 2) / 2
    status, back = sp.decode_frame_ack(sp.encode_frame_ack(sp.Status.ARMED | sp.Status.CLAMPED, measured))
    assert status == sp.Status.ARMED | sp.Status.CLAMPED and np.array_equal(back, measured)
    report = sp.StatusReport(sp.Status.RESTING, measured, 123456, 3, 2, 1)
    again = sp.StatusReport.decode(report.encode())
    assert (again.frames_received, again.crc_errors, again.sequence_gaps, again.watchdog_trips) == (123456, 3, 2, 1)
    assert np.array_equal(again.positions_um, measured)
    assert sp.decode_nak(sp.encode_nak(sp.NakCode.NOT_ARMED, sp.Command.FRAME)) == (3, 6)


def test_measured_positions_saturate_instead_of_wrapping():
    _, back = sp.decode_frame_ack(sp.encode_frame_ack(0, np.full((10, 10), 90.0)))
    assert np.all(back == 63.5)


def test_link_budget_at_700_hz():
    budget = sp.link_budget(rate_hz=700, baud=2_000_000)
    assert budget["min_baud"] == 107 * 10 * 700
    assert budget["frame_utilisation"] < 0.4 and budget["ack_utilisation"] < 0.4


def _packets():
    return [sp.encode_packet(seq=i, command=sp.Command.FRAME, payload=bytes(range(i, i + 100)))
            for i in range(3)] + [sp.encode_packet(seq=9, command=sp.Command.READ_STATUS)]


def test_decoder_resynchronises_after_garbage_truncation_and_crc_errors():
    good = _packets()
    corrupted = bytearray(good[1])
    corrupted[50] ^= 0xFF
    stream = b"\x00\xa5\xa5junk" + good[0] + good[1][:40] + bytes(corrupted) + b"\xa5" + good[2] + good[3]
    decoder = sp.StreamDecoder()
    packets = decoder.feed(stream)
    assert [p.seq for p in packets] == [0, 2, 9]
    assert decoder.counters.crc_errors >= 1
    assert decoder.counters.skipped_bytes > 0


@given(st.lists(st.integers(min_value=1, max_value=50), min_size=1, max_size=40))
@settings(max_examples=60, deadline=None)
def test_decoder_gives_the_same_packets_for_any_chunking(cuts):
    stream = b"".join(_packets())
    decoder = sp.StreamDecoder()
    out, pos = [], 0
    for c in cuts:
        out += decoder.feed(stream[pos:pos + c])
        pos += c
    out += decoder.feed(stream[pos:])
    assert [(p.seq, p.command, p.payload) for p in out] == [(p.seq, p.command, p.payload)
                                                           for p in sp.StreamDecoder().feed(stream)]
    assert len(out) == 4 and out[-1].end == len(stream)


@given(st.binary(max_size=600))
@settings(max_examples=200, deadline=None)
def test_decoder_fuzz_never_crashes_and_only_yields_valid_packets(data):
    decoder = sp.StreamDecoder()
    for packet in decoder.feed(data) + decoder.feed(data[::-1]):
        raw = sp.encode_packet(seq=packet.seq, command=packet.command, payload=packet.payload)
        assert sp.crc16_ccitt(raw[2:-2]) == int.from_bytes(raw[-2:], "big")
    assert decoder.pending <= sp.OVERHEAD + sp.MAX_PAYLOAD


@given(st.binary(max_size=300))
@settings(max_examples=150, deadline=None)
def test_payload_decoders_fuzz_raise_only_protocol_error(data):
    for decode in (sp.decode_frame_ack, sp.StatusReport.decode, sp.Identity.decode, sp.WatchdogConfig.decode,
                   sp.decode_status, sp.decode_nak, sp.decode_positions):
        try:
            decode(data)
        except ProtocolError:
            pass


@given(st.binary(min_size=0, max_size=120), st.integers(0, 255), st.integers(0, 255))
@settings(max_examples=100, deadline=None)
def test_garbage_then_packet_is_always_found(garbage, seq, command):
    packet = sp.encode_packet(seq=seq, command=command, payload=b"xyz")
    found = sp.StreamDecoder().feed(garbage + packet)
    assert (found[-1].seq, found[-1].command, found[-1].payload) == (seq, command, b"xyz")
