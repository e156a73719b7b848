"""Per-frame status codes: one meaning in Python, in Parquet logs and in exported ONNX graphs.

A frame's status is an int64 bit field; 0 means the frame was estimated and every output is
finite. Each set bit names one reason. The estimator sets the bits, the log pipeline stores the
code (``status_code`` column) and its text (``status`` column, :func:`status_messages`), and
exported graphs return the same integer. Frames with a non-zero status have NaN outputs, the rest
of a batch is unaffected. Bit 128 is set by the log pipeline only: in Python and ONNX a contact on
an unknown link is an error when the estimate is called.
"""

from __future__ import annotations

__all__ = ["LOCALIZE_STATUS", "STATUS", "localize_messages", "status_messages"]

#: Per-frame status bits of :attr:`ContactEstimate.status` (0 means ok).
STATUS: dict[int, str] = {
    1: "non-finite F/T reading",
    2: "non-finite joint state or base motion",
    4: "non-finite contact position, direction or wrench",
    8: "zero-length contact direction",
    16: "non-finite measured joint torque",
    32: "non-finite output (the inputs were finite but the computation overflowed)",
    64: "implausible input (joint velocity beyond the URDF limit, or reading beyond sensor range)",
    128: "invalid contact (unknown link or kind, or a link outside every F/T sensor's subtree)",
}


def status_messages(code: int) -> str:
    """Human-readable reason for a status code (``"ok"`` for 0).

    Example:
        >>> status_messages(0), status_messages(1 | 8)
        ('ok', 'non-finite F/T reading; zero-length contact direction')
    """
    if code == 0:
        return "ok"
    return "; ".join(msg for bit, msg in STATUS.items() if code & bit)


#: Per-frame status bits of a contact localization (:class:`torchcontact.localize.Localization`,
#: the ``localize_status_code.<sensor>`` log column); 0 means one contact was found. Frames with
#: a bit other than 16, 64 and 128 set have no contact point.
LOCALIZE_STATUS: dict[int, str] = {
    1: "non-finite F/T reading, joint state or base motion",
    2: "no contact: the force is below the threshold",
    4: "no intersection: the force's line of action misses every candidate link",
    8: "pulling: the line meets the candidate links only where the force would pull (or lies"
    " outside the friction cone)",
    16: "ambiguous: the line enters the links at several distinct points (the first is reported)",
    32: "not localized: the frame has skin contacts in the sensor's region",
    64: "outside the friction cone: no entry where the force lies in the cone (the first entry"
    " is reported)",
    128: "near miss: the line passes beside the links; the nearest edge point is reported",
}


def localize_messages(code: int) -> str:
    """Human-readable reason for a localization status code (``"ok"`` for 0).

    Example:
        >>> localize_messages(16)
        'ambiguous: the line enters the links at several distinct points (the first is reported)'
    """
    if code == 0:
        return "ok"
    return "; ".join(msg for bit, msg in LOCALIZE_STATUS.items() if code & bit)
