"""Fixtures of the driver tests: simulators on a pty and on 127.0.0.1, all without hardware."""

import logging

import numpy as np
import pytest

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

FORCE_ALIAS = 200.0  # Fx = 200.00 N -> 0x4E20 -> little-endian bytes 0x20 0x4E, the header


def ramp_signal(t: float) -> np.ndarray:
    """Every 10 ms frame distinct (fy ramps 1 N per frame), Fx and Fz alias the stream header."""
    k = round(t * 100.0)
    return np.array([FORCE_ALIAS, (k % 300) - 150.0, FORCE_ALIAS, 0.001 * (k % 7), -0.5, 0.25])


def constant_signal(value):
    value = np.asarray(value, dtype=np.float64)
    return lambda t: value.copy()


@pytest.fixture
def rtu_sim():
    from torchcontact.drivers.simulator import RtuSimulator

    sims = []

    def make(**kwargs):
        sim = RtuSimulator(**kwargs).start()
        sims.append(sim)
        return sim

    yield make
    for sim in sims:
        sim.stop()


@pytest.fixture
def tcp_sim():
    from torchcontact.drivers.simulator import TcpSimulator

    sims = []

    def make(**kwargs):
        sim = TcpSimulator(**kwargs).start()
        sims.append(sim)
        return sim

    yield make
    for sim in sims:
        sim.stop()
