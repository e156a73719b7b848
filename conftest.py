"""Test-session settings shared by tests/ and the doctests in torchcontact/.

torch's OpenMP threads spin-wait between parallel regions. On a 2-core machine that also runs the
drivers' simulator threads, a Ray instance or any other busy process, two spinning threads made
small kernels up to 60x slower here (1670 ms vs 28 ms for one RNEA call of 4096 frames) and made
timing-based driver tests flaky. Passive waiting and one intra-op thread keep the suite's speed
independent of the machine's load; throughput is measured in benchmarks/, not in tests.

The suite starts Python processes by the dozen (console scripts, Ray workers, killed runs, the
wheel's bare venv). With ``PYTHONDONTWRITEBYTECODE`` set, as on the development machine, each of
them compiled every module it imported again: 5 s for torch in the wheel's venv (installed with
``--no-compile``), 0.3-1 s for torchcontact from a checkout. The children may write their
bytecode, as a user's install has it (``__pycache__/`` is ignored by git): the wheel test's
children took 28 s instead of 43 s on the 2-core machine.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)  # for the children (this process read it at start)

import torch  # noqa: E402  (after the environment variable: OpenMP reads it at load time)

torch.set_num_threads(1)
