"""Contact wrench estimation from F/T sensors and tactile contact locations, batched.

Del Prete, Natale, Nori, Metta, *Contact Force Estimations Using Tactile Sensors and Force/Torque
Sensors*, HRI 2012, Sec. 2, generalised to several sensors, joint torque sensors and moving bases.

**Regions.** The chosen F/T sensors cut the kinematic tree. The *region* of a sensor is its
subtree (the far side of its joint) minus the subtrees of sensors nested inside it; the bodies on
the root side of every sensor form the root region, where no contact can be estimated (its link to
the world is unmeasured). A contact belongs to the region of its link's body.

**Equations (Sec. 2.1-2.2).** For region ``s`` with reading ``W_s`` (the wrench its sensor's parent
side exerts on the region, in the sensor frame) and nested sensors ``s'`` bordering it, Newton-Euler
of the region's bodies gives, in the sensor frame about its origin::

    sum_k X_k w_k = sum_{i in s} (I_i a_i + v_i x* I_i v_i) - W_s + sum_{s'} W_s' - sum known_k
           A x    =                               b

where ``w_k = [force; moment about the contact point]`` in the contact link's frame and ``X_k``
maps it to the sensor frame (the paper's Eq. 3). The right side is one backward pass of the RNEA
in which each sensor's reading replaces the wrench computed beyond it. A measured joint torque of
a coordinate ``c`` inside the region adds the row ``sum_j S_j^T X_jk w_k = S_j^T F_j - tau_c`` over
the joints ``j`` it drives (the paper's future work).

**Stages** (:mod:`torchcontact.estimation.stages`, each a pure function on scalars of
:mod:`torchcontact._scalar`), chained with the per-frame input checks into one program per robot,
sensor set and slot layout by :mod:`torchcontact.estimation.programs`, run eagerly or compiled
into a kernel by :mod:`torchcontact.kernels`:

1. ``forward``: joint placements, twists, accelerations and body wrenches
   (:mod:`torchcontact.dynamics`);
2. ``region_rhs``: ``b`` of every region, and the torque rows' right sides;
3. ``contact_maps``: each slot's map ``A_k`` (as ``A_k A_k^T``, which for a point force depends
   only on the contact point) and the Gram matrix ``G = sum_k Y_k P_k Y_k^T``, ``Y_k = [A_k; T_k]``;
4. :func:`torchcontact.solve.solve_program`: the minimum-norm solve (pivoted Cholesky), rank and
   residual ``|A x* - b|``;
5. ``contact_wrenches``: ``w_k = P_k Y_k^T y``;
6. ``backward``: joint torques with the estimated contacts (Sec. 2.3): joints on the root side of
   a sensor see its reading;
7. ``covariance``: first-order propagation of each sensor's reading noise.

``P_k`` projects each slot onto its unknowns: ``wrench`` (6), ``force`` (3; zero moment about the
point), ``force_dir`` (1; the magnitude along a unit direction), ``known`` and inactive slots (0).
The frozen value of one layout is :class:`EstimationModel`; :class:`ContactEstimator` is the
public façade.
"""

from torchcontact.contacts import KINDS, Contacts
from torchcontact.estimation.estimator import ConeStatus, ContactEstimate, ContactEstimator
from torchcontact.estimation.layout import EstimationModel, Region, Slot
from torchcontact.status import STATUS, status_messages

__all__ = [
    "KINDS",
    "STATUS",
    "ConeStatus",
    "ContactEstimate",
    "ContactEstimator",
    "Contacts",
    "EstimationModel",
    "Region",
    "Slot",
    "status_messages",
]
