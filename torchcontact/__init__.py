"""torchcontact: batched contact-force estimation from F/T sensors and tactile skin.

Implements and extends Del Prete, Natale, Nori, Metta, *Contact Force Estimations Using Tactile
Sensors and Force/Torque Sensors* (HRI 2012) in PyTorch: a URDF robot model, a batched recursive
Newton-Euler algorithm, and the contact estimator built on it.

The public names below are imported lazily (PEP 562) so that :mod:`torchcontact.runtime`, which
runs exported graphs with onnxruntime and numpy only, can be imported without importing torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# public name -> module it lives in (one per line)
_LAZY = {
    "KINDS": "torchcontact.contacts",
    "LOCALIZE_STATUS": "torchcontact.status",
    "STATUS": "torchcontact.status",
    "Status": "torchcontact.status",
    "InputError": "torchcontact.errors",
    "Localization": "torchcontact.localize",
    "Localizer": "torchcontact.localize",
    "TorchContactError": "torchcontact.errors",
    "BaseMotion": "torchcontact.dynamics",
    "ConeStatus": "torchcontact.estimation",
    "ContactEstimate": "torchcontact.estimation",
    "ContactEstimator": "torchcontact.estimation",
    "Contacts": "torchcontact.contacts",
    "FTSensor": "torchcontact.model",
    "ForcePrior": "torchcontact.constrained",
    "ForwardPass": "torchcontact.dynamics",
    "Frame": "torchcontact.model",
    "FrictionCones": "torchcontact.constrained",
    "PreviousFrame": "torchcontact.constrained",
    "RobotModel": "torchcontact.model",
    "URDFError": "torchcontact.errors",
    "body_wrenches": "torchcontact.dynamics",
    "compiled_inverse_dynamics": "torchcontact.dynamics",
    "forward_pass": "torchcontact.dynamics",
    "inverse_dynamics": "torchcontact.dynamics",
    "robots": None,
    "spatial": None,
    "status_messages": "torchcontact.status",
}

__all__ = [
    "KINDS",
    "LOCALIZE_STATUS",
    "STATUS",
    "BaseMotion",
    "ConeStatus",
    "ContactEstimate",
    "ContactEstimator",
    "Contacts",
    "FTSensor",
    "ForcePrior",
    "ForwardPass",
    "Frame",
    "FrictionCones",
    "InputError",
    "Localization",
    "Localizer",
    "PreviousFrame",
    "RobotModel",
    "Status",
    "TorchContactError",
    "URDFError",
    "__version__",
    "body_wrenches",
    "compiled_inverse_dynamics",
    "forward_pass",
    "inverse_dynamics",
    "robots",
    "spatial",
    "status_messages",
]

if TYPE_CHECKING:  # pragma: no cover - static analysers see the eager imports
    from torchcontact import robots, spatial
    from torchcontact.constrained import ForcePrior, FrictionCones, PreviousFrame
    from torchcontact.dynamics import (
        BaseMotion,
        ForwardPass,
        body_wrenches,
        compiled_inverse_dynamics,
        forward_pass,
        inverse_dynamics,
    )
    from torchcontact.errors import InputError, TorchContactError, URDFError
    from torchcontact.estimation import (
        KINDS,
        STATUS,
        ConeStatus,
        ContactEstimate,
        ContactEstimator,
        Contacts,
        status_messages,
    )
    from torchcontact.localize import Localization, Localizer
    from torchcontact.model import Frame, FTSensor, RobotModel
    from torchcontact.status import LOCALIZE_STATUS, Status


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'torchcontact' has no attribute {name!r}")
    module = _LAZY[name]
    value = (
        importlib.import_module(f"torchcontact.{name}")
        if module is None
        else getattr(importlib.import_module(module), name)
    )
    globals()[name] = value  # cache: later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
