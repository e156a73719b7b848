"""Per-frame status codes: one meaning in Python, in Parquet logs and in exported ONNX graphs.

A frame's status is an int64 bit field; 0 means the frame was estimated and every output is
finite. Each set bit names one reason (:class:`Status`). The estimator sets the bits, the log
pipeline stores the code (``status_code`` column) and its text (``status`` column,
:func:`status_messages`), and exported graphs return the same integer. Frames with a non-zero
status have NaN outputs, the rest of a batch is unaffected, except for
:attr:`Status.NOT_CONVERGED`, a warning: the friction-cone constrained solve did not converge
within its iteration budget (after restarting from the pseudo-inverse when it was warm-started),
and the outputs are its last iterate, inside the cones but not at the optimum; such a frame is not
ok. :attr:`Status.OUTSIDE_TRAINING` is the other warning (:data:`WARNINGS`): ``estimate
--residual`` sets it where a feature of the checkpoint's learned layer lies outside the range it
was trained on (the network extrapolates), and keeps the outputs.
:attr:`Status.INVALID_CONTACT` and :attr:`Status.NOT_DIFFERENTIABLE` are set by the log pipeline
only: in Python and ONNX a contact on an unknown link is an error when the estimate is called, and
derivatives are inputs.

This module imports nothing heavy (the torch-free runtime reads it).
"""

from __future__ import annotations

import enum

__all__ = [
    "DEFAULT_VELOCITY_MARGIN",
    "LOCALIZE_STATUS",
    "STATUS",
    "LocalizeStatus",
    "STATUS_NAMES",
    "Status",
    "WARNINGS",
    "localize_messages",
    "status_bits",
    "status_messages",
]

#: Default ``velocity_margin`` of the log pipeline: a joint faster than twice its URDF velocity
#: limit is implausible (:attr:`Status.IMPLAUSIBLE`).
DEFAULT_VELOCITY_MARGIN = 2.0


class Status(enum.IntFlag):
    """The status bits of a frame (0, ``Status(0)``, means ok).

    Example:
        >>> int(Status.FT_NONFINITE | Status.ZERO_DIRECTION)
        9
    """

    #: a non-finite F/T reading
    FT_NONFINITE = 1
    #: a non-finite joint state or base motion
    JOINT_NONFINITE = 2
    #: a non-finite contact position, direction or wrench of an active slot
    CONTACT_NONFINITE = 4
    #: an active force_dir slot (or pushing cone) with a zero-length direction
    ZERO_DIRECTION = 8
    #: a non-finite measured joint torque where the mask says it is measured
    TORQUE_NONFINITE = 16
    #: the inputs were finite but an output is not (overflow)
    OUTPUT_NONFINITE = 32
    #: joint velocity beyond the URDF limit, or reading beyond sensor range
    IMPLAUSIBLE = 64
    #: a contact on an unknown link or kind, or outside every F/T sensor's subtree (logs only)
    INVALID_CONTACT = 128
    #: the friction-cone constrained solve did not converge (outputs: its last iterate)
    NOT_CONVERGED = 256
    #: qd/qdd derived from a time segment too short to differentiate (logs only)
    NOT_DIFFERENTIABLE = 512
    #: a learned correction's feature outside its training range (outputs kept; logs only)
    OUTSIDE_TRAINING = 1024


_TEXT = {
    Status.FT_NONFINITE: "non-finite F/T reading",
    Status.JOINT_NONFINITE: "non-finite joint state or base motion",
    Status.CONTACT_NONFINITE: "non-finite contact position, direction or wrench",
    Status.ZERO_DIRECTION: "zero-length contact direction",
    Status.TORQUE_NONFINITE: "non-finite measured joint torque",
    Status.OUTPUT_NONFINITE: "non-finite output (the inputs were finite but the computation"
    " overflowed)",
    Status.IMPLAUSIBLE: "implausible input (joint velocity beyond the URDF limit, or reading"
    " beyond sensor range)",
    Status.INVALID_CONTACT: "invalid contact (unknown link or kind, or a link outside every F/T"
    " sensor's subtree)",
    Status.NOT_CONVERGED: "constrained solve not converged within its iteration budget (outputs:"
    " last iterate)",
    Status.NOT_DIFFERENTIABLE: "too few frames to differentiate q (qd/qdd derived from a t_ns"
    " segment of < 3 frames)",
    Status.OUTSIDE_TRAINING: "the learned correction extrapolates (a feature outside its training"
    " range; outputs kept)",
}

#: The warning bits: the frame's outputs are kept (not NaN), but the frame is not ok.
WARNINGS = int(Status.NOT_CONVERGED | Status.OUTSIDE_TRAINING)

#: Per-frame status bits of :attr:`ContactEstimate.status` (0 means ok): bit -> text.
STATUS: dict[int, str] = {int(bit): text for bit, text in _TEXT.items()}

#: A short name per bit of :data:`STATUS` (an identifier: plot legends, rerun entity paths).
STATUS_NAMES: dict[int, str] = {int(bit): bit.name.lower() for bit in Status}


def status_bits(code: int) -> list[str]:
    """Short names (:data:`STATUS_NAMES`) of the bits set in a status code (``[]`` for 0).

    Example:
        >>> status_bits(1 | 64)
        ['ft_nonfinite', 'implausible']
    """
    return [STATUS_NAMES.get(bit, f"bit{bit}") for bit in STATUS if code & bit]


def status_messages(code: int) -> str:
    """Human-readable reason for a status code (``"ok"`` for 0).

    Example:
        >>> status_messages(0), status_messages(1 | 8)
        ('ok', 'non-finite F/T reading; zero-length contact direction')
    """
    if code == 0:
        return "ok"
    return "; ".join(msg for bit, msg in STATUS.items() if code & bit)


class LocalizeStatus(enum.IntFlag):
    """The status bits of a contact localization; 0 means one contact was found.

    Set in :class:`torchcontact.localize.Localization` and the ``localize_status_code.<sensor>``
    log column. Frames with a bit other than ``AMBIGUOUS``, ``OUTSIDE_CONE``, ``NEAR_MISS`` and
    ``PRIOR`` set have no contact point.
    """

    #: a non-finite F/T reading, joint state or base motion
    NONFINITE = 1
    #: the force is below the threshold
    NO_CONTACT = 2
    #: the force's line of action misses every candidate link
    NO_INTERSECTION = 4
    #: the line meets the links only where the force would pull
    PULLING = 8
    #: the line enters the links at several distinct points
    AMBIGUOUS = 16
    #: the frame has skin contacts in the sensor's region
    SKIN_CONTACT = 32
    #: no entry where the force lies in the friction cone
    OUTSIDE_CONE = 64
    #: the line passes beside the links
    NEAR_MISS = 128
    #: ambiguous, resolved by a prior (the previous contact): the entry nearest it is reported
    PRIOR = 256


_LOCALIZE_TEXT = {
    LocalizeStatus.NONFINITE: "non-finite F/T reading, joint state or base motion",
    LocalizeStatus.NO_CONTACT: "no contact: the force is below the threshold",
    LocalizeStatus.NO_INTERSECTION: "no intersection: the force's line of action misses every"
    " candidate link",
    LocalizeStatus.PULLING: "pulling: the line meets the candidate links only where the force"
    " would pull (or lies outside the friction cone)",
    LocalizeStatus.AMBIGUOUS: "ambiguous: the line enters the links at several distinct points"
    " (the first is reported)",
    LocalizeStatus.SKIN_CONTACT: "not localized: the frame has skin contacts in the sensor's"
    " region",
    LocalizeStatus.OUTSIDE_CONE: "outside the friction cone: no entry where the force lies in the"
    " cone (the first entry is reported)",
    LocalizeStatus.NEAR_MISS: "near miss: the line passes beside the links; the nearest edge"
    " point is reported",
    LocalizeStatus.PRIOR: "resolved by the prior: the line enters the links at several points;"
    " the one nearest the contact of a neighbouring frame (or the given prior) is reported",
}

#: Per-frame status bits of a contact localization: bit -> text (see :class:`LocalizeStatus`).
LOCALIZE_STATUS: dict[int, str] = {int(bit): text for bit, text in _LOCALIZE_TEXT.items()}


def localize_messages(code: int) -> str:
    """Human-readable reason for a localization status code (``"ok"`` for 0).

    Example:
        >>> localize_messages(16)
        'ambiguous: the line enters the links at several distinct points (the first is reported)'
    """
    if code == 0:
        return "ok"
    return "; ".join(msg for bit, msg in LOCALIZE_STATUS.items() if code & bit)
