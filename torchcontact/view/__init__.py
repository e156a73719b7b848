"""See the contacts: a robot log and its estimates as an interactive rerun recording.

``torchcontact view LOG [ESTIMATE] --robot URDF`` writes a rerun ``.rrd`` recording (or opens the
viewer) that shows, on the log's own time line (``t_ns``): the robot with its visual meshes posed
by ``q``, every contact with its estimated force (and the truth of a simulated log) as arrows in
one colour per contact slot, each F/T sensor's measured wrench and the residual ``A x - b``, and
time series of the force norms, ranks, unknowns, null-space dimensions, residuals, status bits
(by name) and, for a friction-cone constrained estimate, the cones' activity and convergence.
Frames where a sensor's rank is below its unknowns are marked; their null-space directions are
drawn as arrows on demand (``--nullspace``).

From Python (a notebook, a live stream): :func:`log_to_rerun` draws frames and their estimate,
:class:`RerunScene` keeps drawing into the same recording, :func:`view_log` does what the command
does. Needs the extra ``view`` (``rerun-sdk``, tested with :data:`RERUN_VERSION`).

Names are imported lazily: the command line registers ``view`` without importing rerun, numpy or
torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__all__ = [
    "RERUN_VERSION",
    "LiveView",
    "RerunScene",
    "ViewFrames",
    "log_to_rerun",
    "view_log",
]

_LAZY = {
    "RERUN_VERSION": "torchcontact.view.scene",
    "LiveView": "torchcontact.view.scene",
    "RerunScene": "torchcontact.view.scene",
    "ViewFrames": "torchcontact.view.scene",
    "log_to_rerun": "torchcontact.view.scene",
    "view_log": "torchcontact.view.logs",
}

if TYPE_CHECKING:  # pragma: no cover - static analysers see the eager imports
    from torchcontact.view.logs import view_log
    from torchcontact.view.scene import (
        RERUN_VERSION,
        LiveView,
        RerunScene,
        ViewFrames,
        log_to_rerun,
    )


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'torchcontact.view' has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
