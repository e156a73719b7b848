"""Per-frame status codes: one meaning in Python, in Parquet logs and in exported ONNX graphs.

A frame's status is an int64 bit field; 0 means the frame was estimated and every output is
finite. Each set bit names one reason. The estimator sets the bits, the log pipeline stores the
code (``status_code`` column) and its text (``status`` column, :func:`status_messages`), and
exported graphs return the same integer. Frames with a non-zero status have NaN outputs, the rest
of a batch is unaffected. Bit 128 is set by the log pipeline only: in Python and ONNX a contact on
an unknown link is an error when the estimate is called.
"""

from __future__ import annotations

__all__ = ["STATUS", "STATUS_NAMES", "status_bits", "status_messages"]

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


#: A short name per bit of :data:`STATUS` (an identifier: plot legends, rerun entity paths).
STATUS_NAMES: dict[int, str] = {
    1: "ft_nonfinite",
    2: "joints_nonfinite",
    4: "contact_nonfinite",
    8: "zero_direction",
    16: "tau_nonfinite",
    32: "output_nonfinite",
    64: "implausible_input",
    128: "invalid_contact",
}


def status_bits(code: int) -> list[str]:
    """Short names (:data:`STATUS_NAMES`) of the bits set in a status code (``[]`` for 0).

    Example:
        >>> status_bits(1 | 64)
        ['ft_nonfinite', 'implausible_input']
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
