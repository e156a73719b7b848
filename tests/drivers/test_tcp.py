"""Generic Modbus F/T sensors against a pymodbus ModbusTcpServer on 127.0.0.1."""

import time

import numpy as np
import pytest

from torchcontact.drivers import FTConnectionError, ModbusFTSensor, SampleFlags
from torchcontact.drivers.simulator import Faults, constant_signal

WRENCH = [1.5, -2.25, 100.0, 0.125, -0.5, 3.0]


@pytest.mark.parametrize("profile", ["generic-float32", "robotiq-ft300"])
def test_poll_values(tcp_sim, profile):
    sim = tcp_sim(profile=profile, signal=constant_signal(WRENCH))
    with ModbusFTSensor(profile, host="127.0.0.1", tcp_port=sim.port) as ft:
        samples = [ft.read(0.5) for _ in range(5)]
    assert all(s is not None for s in samples)
    atol = 0 if profile == "generic-float32" else 1e-12  # float32 values here are exact
    np.testing.assert_allclose(samples[-1].wrench, WRENCH, atol=atol)
    assert [s.seq for s in samples] == list(range(5))
    assert sim.stats.requests >= 5


def test_tare_and_hardware_zero(tcp_sim):
    sim = tcp_sim(profile="generic-float32", signal=constant_signal(WRENCH))
    with ModbusFTSensor("generic-float32", host="127.0.0.1", tcp_port=sim.port) as ft:
        bias = ft.tare(10)
        np.testing.assert_allclose(bias, WRENCH)
        s = ft.read(0.5)
        assert s.flags & SampleFlags.TARED
        np.testing.assert_allclose(s.wrench, 0.0, atol=1e-6)
        ft.untare()
        ft.zero()  # FC16 to the profile's zero register: the simulator subtracts its reading
        np.testing.assert_allclose(ft.read(0.5).wrench, 0.0, atol=1e-6)


def test_refused_requests_counted(tcp_sim):
    sim = tcp_sim(profile="generic-float32", faults=Faults(drop=0.3, seed=2))
    with ModbusFTSensor("generic-float32", host="127.0.0.1", tcp_port=sim.port) as ft:
        results = [ft.read(0.5) for _ in range(60)]
    refused = sum(r is None for r in results)
    assert refused == sim.stats.exceptions > 0
    assert ft.modbus_errors == refused and ft.stats.frames == 60 - refused


def test_dropped_connections_reconnect(tcp_sim):
    sim = tcp_sim(profile="generic-float32", faults=Faults(disconnect_every_s=0.3))
    ft = ModbusFTSensor("generic-float32", host="127.0.0.1", tcp_port=sim.port, timeout=0.2)
    ft.open()
    seqs, end = [], time.monotonic() + 1.5
    while time.monotonic() < end:
        s = ft.read(0.2)
        if s is not None:
            seqs.append(s.seq)
    ft.close()
    assert sim.stats.disconnects >= 3
    assert ft.stats.reconnects >= 1
    assert seqs == list(range(len(seqs))) and len(seqs) > 50  # polling resumes, no gaps


def test_slow_server_times_out_quickly(tcp_sim):
    sim = tcp_sim(profile="generic-float32", faults=Faults(delay_s=0.3))
    ft = ModbusFTSensor(
        "generic-float32",
        host="127.0.0.1",
        tcp_port=sim.port,
        timeout=0.05,
        max_consecutive_timeouts=100,
    )
    ft.open()
    t = time.monotonic()
    assert ft.read(0.05) is None
    assert time.monotonic() - t < 0.25  # not the pymodbus default of 3 s x 3 retries
    assert ft.stats.timeouts == 1
    time.sleep(0.4)
    # a late answer to the timed-out request is not returned as a new sample
    for _ in range(3):
        s = ft.read(0.05)
        assert s is None
    ft.close()


def test_connection_refused_is_named():
    ft = ModbusFTSensor("generic-float32", host="127.0.0.1", tcp_port=1, timeout=0.1)
    with pytest.raises(FTConnectionError, match="127.0.0.1:1"):
        ft.open()


def test_bad_arguments():
    with pytest.raises(ValueError, match="exactly one of port"):
        ModbusFTSensor("generic-float32")
