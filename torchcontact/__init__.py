"""torchcontact: batched contact-force estimation from F/T sensors and tactile skin.

Implements and extends Del Prete, Natale, Nori, Metta, *Contact Force Estimations Using Tactile
Sensors and Force/Torque Sensors* (HRI 2012) in PyTorch: a URDF robot model, a batched recursive
Newton-Euler algorithm, and the contact estimator built on it.
"""

from torchcontact import robots, spatial
from torchcontact.dynamics import (
    BaseMotion,
    ForwardPass,
    body_wrenches,
    compiled_inverse_dynamics,
    forward_pass,
    inverse_dynamics,
)
from torchcontact.estimation import (
    KINDS,
    STATUS,
    ContactEstimate,
    ContactEstimator,
    Contacts,
    status_messages,
)
from torchcontact.model import Frame, FTSensor, RobotModel, URDFError

__version__ = "0.1.0"

__all__ = [
    "KINDS",
    "STATUS",
    "BaseMotion",
    "ContactEstimate",
    "ContactEstimator",
    "Contacts",
    "FTSensor",
    "ForwardPass",
    "Frame",
    "RobotModel",
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
