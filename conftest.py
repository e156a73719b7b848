"""Test-session settings shared by tests/ and the doctests in torchcontact/.

torch's OpenMP threads spin-wait between parallel regions. On a 2-core machine that also runs the
drivers' simulator threads, a Ray instance or any other busy process, two spinning threads made
small kernels up to 60x slower here (1670 ms vs 28 ms for one RNEA call of 4096 frames) and made
timing-based driver tests flaky. Passive waiting and one intra-op thread keep the suite's speed
independent of the machine's load; throughput is measured in benchmarks/, not in tests.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402  (after the environment variable: OpenMP reads it at load time)

torch.set_num_threads(1)
