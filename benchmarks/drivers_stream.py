"""Benchmark of the F/T drivers over the simulators (no hardware).

Measures: FT 300 stream mode over the pty simulator (frames received vs the 100 Hz frame slots
the simulator sent, dropped), polling rates over Modbus TCP (pymodbus server on 127.0.0.1) and
over the pty RTU (paced at 19200 baud), and the end-to-end latency from sensor frame (host
receive time) to published estimate through the live loop with a trivial estimator.

Usage: python benchmarks/drivers_stream.py [--seconds 60]
"""

import argparse
import logging
import platform
import socket
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _meta import git_commit  # noqa: E402

from torchcontact.drivers import ModbusFTSensor, RobotiqFT300  # noqa: E402
from torchcontact.drivers.live import LiveLoop, UdpPublisher, passthrough_estimator  # noqa: E402
from torchcontact.drivers.simulator import (  # noqa: E402
    RtuSimulator,
    TcpSimulator,
    frame_pattern_signal,
)
from torchcontact.drivers.stream import STREAM_SCALE  # noqa: E402

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def metadata():
    import pymodbus
    import serial

    commit = git_commit()
    return {
        "commit": commit,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "pymodbus": pymodbus.__version__,
        "pyserial": serial.__version__,
        "platform": platform.platform(),
        "cpus": str(__import__("os").cpu_count()),
    }


def bench_stream(seconds):
    with RtuSimulator(signal=frame_pattern_signal(), record=True) as sim:
        ft = RobotiqFT300(sim.port, stream=True, read_identity=False)
        ft.open()
        got = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            s = ft.read(0.05)
            if s is not None:
                got.append(tuple(np.rint(s.wrench / STREAM_SCALE).astype(int)))
        stats = ft.stats.as_dict()
        ft.close()
        # match received frames in order against what the simulator sent (the pattern repeats
        # after 2100 frames, so walk both lists instead of a lookup)
        sent = [tuple(w) for w in sim.stats.sent_wrenches]
        j, slots, unmatched = 0, [], 0
        for g in got:
            while j < len(sent) and sent[j] != g:
                j += 1
            if j == len(sent):
                unmatched += 1
                break
            slots.append(sim.stats.sent_slots[j])
            j += 1
        sent_in_window = slots[-1] - slots[0] + 1  # 100 Hz slots between first and last read
        return {
            "stream frames received": len(got),
            "stream frame slots in window (100 Hz)": sent_in_window,
            "stream received rate (Hz)": len(got) / seconds,
            "stream lost in window (simulator truth)": sent_in_window - len(got),
            "stream dropped (driver count)": stats["dropped"],
            "stream frames not matching a sent frame": unmatched,
            "stream crc errors": stats["crc_errors"],
            "stream timeouts": stats["timeouts"],
        }


def poll_rate(ft, seconds):
    ft.open()
    n, end = 0, time.monotonic() + seconds
    t0 = time.monotonic()
    while time.monotonic() < end:
        n += ft.read(0.2) is not None
    rate = n / (time.monotonic() - t0)
    timeouts = ft.stats.timeouts
    ft.close()
    return rate, timeouts


def bench_poll(seconds):
    with TcpSimulator("generic-float32") as sim:
        tcp, _ = poll_rate(
            ModbusFTSensor("generic-float32", host="127.0.0.1", tcp_port=sim.port), seconds
        )
    with RtuSimulator() as sim:
        rtu, rtu_to = poll_rate(RobotiqFT300(sim.port, read_identity=False), seconds)
    return {
        "poll rate Modbus TCP, generic-float32 (Hz)": tcp,
        "poll rate RTU pty @19200 baud, FT 300 (Hz)": rtu,
        "poll RTU timeouts": rtu_to,
    }


def bench_latency(seconds):
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    with RtuSimulator() as sim:
        ft = RobotiqFT300(sim.port, stream=True, read_identity=False)
        ft.open()
        loop = LiveLoop(ft, None, passthrough_estimator, [UdpPublisher(*rx.getsockname())])
        s = loop.run(duration=seconds)
        ft.close()
    rx.close()
    return {
        "live loop frames published": s["published"],
        "latency frame->publish p50 (us)": s["latency_p50_us"],
        "latency frame->publish p99 (us)": s["latency_p99_us"],
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="stream test duration")
    args = ap.parse_args()
    meta = metadata()
    side = min(args.seconds, 10.0)
    results = {}
    results.update(bench_stream(args.seconds))
    results.update(bench_poll(min(args.seconds, 5.0)))
    results.update(bench_latency(side))
    print("# drivers_stream benchmark (simulators, no hardware)")
    for k, v in meta.items():
        print(f"# {k}: {v}")
    print(
        f"# stream seconds: {args.seconds}, poll seconds: {min(args.seconds, 5.0)}, "
        f"live-loop seconds: {side}"
    )
    width = max(len(k) for k in results)
    print(f"| {'metric'.ljust(width)} | value      |")
    print(f"|{'-' * (width + 2)}|------------|")
    for k, v in results.items():
        val = f"{v:.1f}" if isinstance(v, float) else str(v)
        print(f"| {k.ljust(width)} | {val:>10} |")


if __name__ == "__main__":
    main()
