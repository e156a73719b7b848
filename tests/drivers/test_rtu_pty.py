"""FT 300 over a pseudo-terminal: exact bytes, polling, stream mode, fault injection."""

import time

import numpy as np
import pytest
import serial

from torchcontact.drivers import FTConnectionError, RobotiqFT300, SampleFlags
from torchcontact.drivers._crc import with_crc
from torchcontact.drivers.simulator import Faults, constant_signal, frame_pattern_signal
from torchcontact.drivers.stream import STREAM_SCALE, StreamParser, encode_stream_frame

WRENCH = [200.0, -0.01, 1.5, 1.0, -32.768, 0.007]  # -> registers 20000 FFFF 150 1000 8000 7


def raw_port(sim):
    return serial.Serial(sim.port, 19200, timeout=0.3)


def exchange(port, request, n):
    port.reset_input_buffer()
    port.write(request)
    return port.read(n)


def test_fc03_response_bytes(rtu_sim):
    sim = rtu_sim(signal=constant_signal(WRENCH), line_rate=False)
    with raw_port(sim) as port:
        reply = exchange(port, with_crc(bytes.fromhex("090300B40006")), 17)
    assert reply == with_crc(bytes.fromhex("09030C4E20FFFF009603E880000007"))
    assert reply[:3] == bytes([0x09, 0x03, 12])


def test_exceptions_and_foreign_ids(rtu_sim):
    sim = rtu_sim(line_rate=False)
    with raw_port(sim) as port:
        # FC04 is not implemented by the FT 300: illegal function
        assert exchange(port, with_crc(bytes.fromhex("090400B40006")), 5) == with_crc(
            b"\x09\x84\x01"
        )
        # unmapped register: illegal data address
        assert exchange(port, with_crc(bytes.fromhex("090300000001")), 5) == with_crc(
            b"\x09\x83\x02"
        )
        # another device id or a bad CRC: silence
        assert exchange(port, with_crc(bytes.fromhex("010300B40006")), 17) == b""
        assert exchange(port, bytes.fromhex("090300B40006FFFF"), 17) == b""
        # identity registers
        reply = exchange(port, with_crc(bytes.fromhex("090302020001")), 7)
        assert reply == with_crc(bytes.fromhex("09030207E3"))  # year 2019


def test_stream_start_echo_frames_and_stop(rtu_sim):
    sim = rtu_sim(signal=constant_signal(WRENCH), line_rate=False)
    start = bytes.fromhex("0910019A0001020200CDCA")
    with raw_port(sim) as port:
        port.write(start)
        assert port.read(8) == with_crc(bytes.fromhex("0910019A0001"))
        data = port.read(16 * 5)
        frame = encode_stream_frame([20000, -1, 150, 1000, -32768, 7])
        assert data == frame * 5
        # while streaming the sensor answers no Modbus request
        port.write(with_crc(bytes.fromhex("090300B40006")))
        time.sleep(0.05)
        after = port.read(port.in_waiting)
        assert b"\x09\x03\x0c" not in after  # no FC03 response, only whole stream frames
        parser = StreamParser()
        assert parser.feed(after) and parser.stats.crc_errors == 0 and parser.buffered == 0
        # ~0.5 s of 0xFF at line rate stops it
        for _ in range(25):
            port.write(b"\xff" * 38)
            time.sleep(0.02)
        time.sleep(0.05)
        port.reset_input_buffer()
        time.sleep(0.1)
        assert port.in_waiting == 0
    assert sim.stats.stream_starts == 1 and sim.stats.stream_stops == 1


def test_polling_driver_values_and_identity(rtu_sim):
    sim = rtu_sim(signal=constant_signal(WRENCH), faults=Faults(streaming_at_start=True))
    with RobotiqFT300(sim.port) as ft:  # stop bytes first: the sensor was streaming
        assert ft.identity["firmware"] == "V1.0.4"
        assert (ft.identity["serial"], ft.identity["year"]) == (123456, 2019)
        samples = [ft.read(0.2) for _ in range(5)]
        np.testing.assert_allclose(ft.read_extra()["az"], -1.0)
    assert sim.stats.stream_stops == 1
    assert all(s is not None for s in samples)
    np.testing.assert_allclose(samples[0].wrench, WRENCH, atol=1e-12)
    assert [s.seq for s in samples] == [0, 1, 2, 3, 4]
    assert all(b.t_ns > a.t_ns for a, b in zip(samples, samples[1:], strict=False))


def received_subsequence(received, sent):
    """Whether ``received`` appears in ``sent`` in order, each frame at most once."""
    it = iter(map(tuple, sent))
    return all(any(r == s for s in it) for r in map(tuple, received))


def counts(sample):
    return tuple(np.rint(sample.wrench / STREAM_SCALE).astype(int))


def read_for(ft, seconds):
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        s = ft.read(0.05)
        if s is not None:
            out.append(s)
    return out


def test_stream_driver_gets_every_frame_in_order(rtu_sim):
    sim = rtu_sim(
        signal=frame_pattern_signal(), faults=Faults(streaming_at_start=True), record=True
    )
    ft = RobotiqFT300(sim.port, stream=True, read_identity=False)
    ft.open()
    samples = read_for(ft, 1.0)
    ft.close()
    sent = list(sim.stats.sent_wrenches)
    got = [counts(s) for s in samples]
    assert 90 <= len(got) <= 110
    assert received_subsequence(got, sent)
    # consecutive frames: no loss in a clean run, all aliasing Fx = 200 N frames recovered
    first = [tuple(x) for x in sent].index(got[0])
    assert got == [tuple(x) for x in sent[first : first + len(got)]]
    assert ft.stats.dropped == 0 and ft.stats.crc_errors == 0
    assert [s.seq for s in samples] == list(range(len(samples)))
    assert all(s.flags & SampleFlags.STREAM for s in samples)


def test_stream_faults_counted_never_invented(rtu_sim):
    faults = Faults(drop=0.05, corrupt=0.05, split=0.3, delay_s=0.002, seed=3)
    sim = rtu_sim(signal=frame_pattern_signal(), faults=faults, record=True)
    ft = RobotiqFT300(sim.port, stream=True, read_identity=False)
    ft.open()
    samples = read_for(ft, 1.5)
    ft.close()
    got = [counts(s) for s in samples]
    sent = [tuple(x) for x in sim.stats.sent_wrenches]
    assert received_subsequence(got, sent)
    assert len(set(got)) == len(got)  # never repeated
    first, last = sent.index(got[0]), sent.index(got[-1])
    lost_good = (last - first + 1) - len(got)  # intact frames sent in the window but not read
    assert lost_good == 0
    # every frame the sensor failed to deliver in the window shows as a seq gap
    lost_total = samples[-1].seq - samples[0].seq + 1 - len(samples)
    assert ft.stats.crc_errors >= 1
    assert lost_total > 0 and ft.stats.dropped == lost_total
    assert all(b.seq > a.seq for a, b in zip(samples, samples[1:], strict=False))
    gaps = [b for a, b in zip(samples, samples[1:], strict=False) if b.seq - a.seq > 1]
    assert all(s.flags & SampleFlags.AFTER_GAP for s in gaps)
    # the count matches what the simulator really lost between the first and last frame read
    slot = dict(zip(sent, sim.stats.sent_slots, strict=True))
    true_lost = slot[got[-1]] - slot[got[0]] + 1 - len(got)
    assert true_lost > 0
    assert abs(lost_total - true_lost) <= 1


def test_unplug_reconnects_and_resumes(rtu_sim):
    faults = Faults(disconnect_every_s=1.2, disconnect_s=0.2, seed=1)
    sim = rtu_sim(signal=frame_pattern_signal(), faults=faults, record=True)
    ft = RobotiqFT300(sim.port, stream=True, read_identity=False, backoff_initial=0.05)
    ft.open()
    samples = read_for(ft, 3.0)
    ft.close()
    assert sim.stats.disconnects >= 1
    assert ft.stats.reconnects >= 1
    assert any(s.flags & SampleFlags.RECONNECTED for s in samples)
    got = [counts(s) for s in samples]
    assert received_subsequence(got, [tuple(x) for x in sim.stats.sent_wrenches])
    seqs = [s.seq for s in samples]
    assert seqs == sorted(set(seqs))
    after = [i for i, s in enumerate(samples) if s.flags & SampleFlags.RECONNECTED][0]
    # the outage (unplug + stop bytes + restart) is counted as lost frames
    assert samples[after].seq - samples[after - 1].seq > 20
    assert len(samples) - after > 20  # and the stream resumed


def test_bad_port_is_named():
    ft = RobotiqFT300("/dev/does-not-exist-ttyUSB9")
    with pytest.raises(FTConnectionError, match="does-not-exist-ttyUSB9"):
        ft.open()
