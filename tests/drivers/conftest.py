"""Fixtures of the driver tests: simulators on a pty and on 127.0.0.1, all without hardware."""

import logging

import pytest

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


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
