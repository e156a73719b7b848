"""torchcontact: batched contact-force estimation from F/T sensors and tactile skin.

Implements and extends Del Prete, Natale, Nori, Metta, *Contact Force Estimations Using Tactile
Sensors and Force/Torque Sensors* (HRI 2012) in PyTorch: a URDF robot model, a batched recursive
Newton-Euler algorithm, and the contact estimator built on it.
"""

__version__ = "0.1.0"

__all__ = [
    "__version__",
]
