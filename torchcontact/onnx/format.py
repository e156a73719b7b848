"""The contract between the ONNX writer and reader: names, metadata keys, layouts (torch-free).

:mod:`torchcontact.onnx.export` writes graphs and :mod:`torchcontact.onnx.runtime` reads them;
both import every name of the contract from here, and from nowhere else:

* the format tags (:data:`ESTIMATOR_FORMAT`, :data:`RESIDUAL_FORMAT`,
  :data:`RESIDUAL_GRAPH_FORMAT`);
* the input and output names of the graphs (:data:`INPUTS`: one name per input across the
  estimator program, the graphs, the runtime and the docs, with the old spellings still accepted);
* every ``metadata_props`` key (:class:`Key`) and the JSON encoding of the values
  (:func:`encode`, :func:`decode`);
* the packed vectors of the single-frame graph (:class:`StepLayout`);
* the column selector of correction graphs (:func:`selection`);
* the robot identity recorded in a graph (:func:`recorded_identity`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from torchcontact.identity import RobotIdentity

__all__ = [
    "CONE_INPUTS",
    "CONE_OUTPUTS",
    "ESTIMATOR_FORMAT",
    "ESTIMATOR_INPUTS",
    "ESTIMATOR_OUTPUTS",
    "INPUTS",
    "RESIDUAL_FORMAT",
    "RESIDUAL_FORMATS",
    "RESIDUAL_GRAPH_FORMAT",
    "InputName",
    "Key",
    "StepLayout",
    "canonical",
    "decode",
    "encode",
    "recorded_identity",
    "selection",
    "state_in",
    "state_out",
]

#: Format of the estimator graphs (``metadata_props["format"]``).
ESTIMATOR_FORMAT = "torchcontact.estimator/2"
#: A learned residual model ``features -> residual`` (:func:`~torchcontact.onnx.export_residual`).
RESIDUAL_FORMAT = "torchcontact.residual/1"
#: A correction stack from raw joint state (:func:`~torchcontact.onnx.export_residual_checkpoint`).
RESIDUAL_GRAPH_FORMAT = "torchcontact.residual-graph/1"
#: Formats of residual-correction graphs the exporter chains and the runtime runs.
RESIDUAL_FORMATS = (RESIDUAL_FORMAT, RESIDUAL_GRAPH_FORMAT)


@dataclass(frozen=True)
class InputName:
    """One per-frame input: its name everywhere, shape, unit, frame and other spellings.

    Attributes:
        name: the one name (program input, graph input, step layout field, runtime key).
        shape: per-frame shape in symbols (``nv`` joints, ``S`` sensors, ``K`` slots).
        unit: SI unit.
        meaning: what it is, in which frame.
        log: the column (or contact field) of the log format that holds it.
        aliases: older spellings still accepted where users pass inputs by name.
    """

    name: str
    shape: str
    unit: str
    meaning: str
    log: str
    aliases: tuple[str, ...] = ()


#: Every per-frame input of the estimator, in graph input order (optional groups after the
#: fixed ones). ``docs/names.md`` renders this table (a test keeps them equal).
INPUTS: tuple[InputName, ...] = (
    InputName("q", "nv", "rad or m", "joint positions, joint_names order", "q"),
    InputName("qd", "nv", "rad/s or m/s", "joint velocities", "qd"),
    InputName("qdd", "nv", "rad/s^2 or m/s^2", "joint accelerations", "qdd"),
    InputName("ft", "S, 6", "N, N m", "F/T readings [force; moment], sensor frame and direction",
              "ft.<sensor>"),
    InputName("positions", "K, 3", "m", "contact points, slot link frame",
              "contacts[].position", ("pos", "position")),
    InputName("directions", "K, 3", "1", "force directions of force_dir slots, link frame",
              "contacts[].direction", ("dir", "direction")),
    InputName("wrenches", "K, 6", "N, N m", "wrenches of known slots, link frame, about the point",
              "contacts[].wrench", ("wrench",)),
    InputName("active", "K", "1", "1 where the slot is in contact", "contacts[] present"),
    InputName("ft_residual", "S, 6", "N, N m", "subtracted from ft (a further correction)",
              "(none)"),
    InputName("omega", "3", "rad/s", "base angular velocity, root frame", "base.omega"),
    InputName("domega", "3", "rad/s^2", "base angular acceleration, root frame", "base.domega"),
    InputName("proper_acc", "3", "m/s^2", "base proper acceleration (IMU), root frame",
              "base.acc", ("acc",)),
    InputName("tau_measured", "nv", "N m or N", "measured joint torques", "tau_measured",
              ("tau_meas",)),
    InputName("tau_mask", "nv", "1", "1 where a joint torque is measured",
              "finite entries of tau_measured"),
    InputName("ft_cov", "S, 6, 6", "N^2, N^2 m^2", "reading noise covariance, sensor frame",
              "(none)", ("ft_covariance",)),
    InputName("normals", "K, 3", "1", "outward surface normals (friction cones), link frame",
              "contacts[].normal", ("normal",)),
    InputName("friction", "K", "1", "friction coefficients (friction cones)",
              "contacts[].friction"),
    InputName("pushing", "K", "1", "1 where the contact can only push (friction cones)",
              "contacts[].pushing"),
    InputName("extra", "E", "as logged", "extra columns read by chained corrections",
              "<column>"),
)  # fmt: skip

_ALIASES = {a: i.name for i in INPUTS for a in (i.name, *i.aliases)}


def canonical(name: str) -> str:
    """The one name of an input given by any of its spellings (unknown names are returned).

    Example:
        >>> canonical("tau_meas"), canonical("positions"), canonical("h_in.base_ft")
        ('tau_measured', 'positions', 'h_in.base_ft')
    """
    return _ALIASES.get(name, name)


#: Inputs of every batched estimator graph, in order.
ESTIMATOR_INPUTS = ("q", "qd", "qdd", "ft", "positions", "directions", "wrenches", "active",
                    "ft_residual")  # fmt: skip
#: Inputs of a moving base, of torque rows, of the covariance (after :data:`ESTIMATOR_INPUTS`).
BASE_INPUTS = ("omega", "domega", "proper_acc")
TORQUE_INPUTS = ("tau_measured", "tau_mask")
COVARIANCE_INPUT = "ft_cov"
#: Outputs of the batched estimator graph, in order.
ESTIMATOR_OUTPUTS = ("force", "moment", "joint_torques", "rank", "unknowns", "residual", "status")
#: Inputs a constrained estimator graph takes after the fixed-base ones.
CONE_INPUTS = ("normals", "friction", "pushing")
#: Outputs a constrained estimator graph returns after :data:`ESTIMATOR_OUTPUTS`.
CONE_OUTPUTS = ("converged", "iterations", "cone_active")
#: Inputs that have no default (the others default to zeros, ``active`` and ``pushing`` to 1).
REQUIRED = ("q", "qd", "qdd", "ft", "omega", "domega", "proper_acc", "tau_measured", "ft_cov",
            "normals", "friction")  # fmt: skip
#: Inputs whose default is 1.
ONES = ("active", "pushing")
#: Input of the extra columns of chained corrections.
EXTRA = "extra"


def state_in(sensor: str) -> str:
    """Input name of a chained recurrent correction's state, ``h_in.<sensor>``."""
    return f"h_in.{sensor}"


def state_out(sensor: str) -> str:
    """Output name of a chained recurrent correction's next state, ``h_out.<sensor>``."""
    return f"h_out.{sensor}"


class Key:
    """The ``metadata_props`` keys of the graphs (written and read through these names only)."""

    # every graph
    FORMAT = "format"
    OPSET = "opset"
    TORCH_VERSION = "torch_version"
    DTYPE = "dtype"
    INPUTS = "inputs"
    INPUT_SHAPES = "input_shapes"
    OUTPUTS = "outputs"
    UNITS = "units"
    JOINT_NAMES = "joint_names"
    ROBOT = "robot"
    #: sha256 of the URDF text (what graphs of earlier versions were checked by)
    URDF_SHA256 = "urdf_sha256"
    #: :class:`~torchcontact.identity.RobotIdentity` entries and their hash
    ROBOT_IDENTITY = "robot_identity"
    ROBOT_IDENTITY_SHA256 = "robot_identity_sha256"
    # estimator graphs
    GRAPH = "graph"
    SENSORS = "sensors"
    SLOT_LINKS = "slot_links"
    SLOT_KINDS = "slot_kinds"
    FRAMES = "frames"
    GRAVITY = "gravity"
    MOVING_BASE = "moving_base"
    TORQUE_ROWS = "torque_rows"
    COVARIANCE = "covariance"
    VELOCITY_MARGIN = "velocity_margin"
    FT_RANGE = "ft_range"
    SOLVER = "solver"
    RANK_RTOL = "rank_rtol"
    TORQUE_JOINTS = "torque_joints"
    RESIDUALS = "residuals"
    BATCHED_GRAPH = "batched_graph"
    STEP_GRAPH = "step_graph"
    STEP_INPUTS = "step_inputs"
    STEP_OUTPUTS = "step_outputs"
    CONSTRAINTS = "constraints"
    #: the noise the solve is weighted by (graphs exported with ``ft_noise``; absent: the
    #: unweighted ``pinv(A) b``): :meth:`torchcontact.logs.noise.FTNoise.summary`
    FT_NOISE = "ft_noise"
    #: per sensor the layout of the online inputs (step graphs exported with ``online``, C
    #: libraries): :meth:`torchcontact.online.state.SensorLayout.to_json`
    ONLINE = "online"
    #: per contact slot the index of the sensor whose region it lies in (with ``online``)
    SLOT_REGIONS = "slot_regions"
    #: estimators exported with ``localize`` (the step graph localizes; the key is in both
    #: graphs' metadata): ``{graph, link, slot, region, sensor, force_threshold, mesh, faces,
    #: outputs}`` (:mod:`torchcontact.onnx.step.localize`); absent: no localization
    LOCALIZE = "localize"
    VERSION = "torchcontact_version"
    # correction graphs
    SENSOR = "sensor"
    #: the URDF text hash a correction was trained on (earlier versions) or its identity hash
    ROBOT_SHA256 = "robot_sha256"
    RECURRENT = "recurrent"
    STATE_SHAPE = "state_shape"
    FEATURES = "features"
    FEATURE_NAMES = "feature_names"
    EXTRA_COLUMNS = "extra_columns"
    LAYERS = "layers"
    INERTIAL = "inertial"
    STACK = "stack"
    LEARNED_GRAPH = "learned_graph"
    SHA256_WEIGHTS = "sha256_weights"
    DATA_SHA256 = "data_sha256"
    CHECKPOINT_WEIGHTS_SHA256 = "checkpoint_weights_sha256"
    MODEL_VERSION = "model_version"


def encode(meta: Mapping[str, Any]) -> dict[str, str]:
    """``metadata_props`` values: strings as they are, everything else as JSON."""
    return {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in meta.items()}


def decode(props: Mapping[str, str]) -> dict[str, Any]:
    """Inverse of :func:`encode` (values that are not JSON stay strings)."""
    out: dict[str, Any] = {}
    for k, v in props.items():
        try:
            out[k] = json.loads(v)
        except (ValueError, TypeError):
            out[k] = v
    return out


class StepLayout:
    """Packed input or output vector of the single-frame graph: field -> (offset, shape).

    Written to the metadata as ``{name: [offset, shape]}`` (:meth:`as_dict`).
    """

    def __init__(self) -> None:
        self.fields: dict[str, tuple[int, tuple[int, ...]]] = {}
        self.size = 0

    def add(self, name: str, shape: tuple[int, ...]) -> int:
        """Append a field; returns its offset."""
        off = self.size
        self.fields[name] = (off, tuple(shape))
        self.size += math.prod(shape)
        return off

    def index(self, name: str, *idx: int) -> int:
        """Flat position of element ``idx`` of field ``name``."""
        off, shape = self.fields[name]
        return off + (int(np.ravel_multi_index(idx, shape)) if shape else 0)

    def span(self, name: str) -> tuple[int, int, tuple[int, ...]]:
        """``(start, stop, shape)`` of a field."""
        off, shape = self.fields[name]
        return off, off + math.prod(shape), shape

    def as_dict(self) -> dict[str, list]:
        """JSON-ready ``{name: [offset, shape]}``."""
        return {k: [o, list(s)] for k, (o, s) in self.fields.items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Sequence]) -> StepLayout:
        """Inverse of :meth:`as_dict`."""
        lay = cls()
        for k, (o, shape) in d.items():
            lay.fields[k] = (int(o), tuple(int(s) for s in shape))
            lay.size = max(lay.size, int(o) + math.prod(int(s) for s in shape))
        return lay


def selection(cols: Sequence[tuple[str, str]], position) -> np.ndarray:
    """The 0/1 matrix picking a correction graph's input columns from a flat source.

    One column selector for the three places that feed corrections: the batched graph
    (source ``[q, qd, qdd, extra]``), the single-frame graph (the packed input) and the runtime.

    Args:
        cols: per column ``("q" | "qd" | "qdd", joint)`` or ``("extra", name)``.
        position: ``(kind, key) -> index`` into the source; its ``size`` attribute (or the
            largest index + 1) gives the number of rows.

    Returns:
        ``(rows, len(cols))`` float64.
    """
    idx = [int(position(kind, key)) for kind, key in cols]
    rows = int(getattr(position, "size", max(idx, default=-1) + 1))
    sel = np.zeros((rows, len(cols)))
    sel[idx, np.arange(len(cols))] = 1.0
    return sel


class JointColumns:
    """Positions in ``[q, qd, qdd, extra]`` (per frame) of joint and extra columns.

    Args:
        joint_names: the order of ``q``, ``qd``, ``qdd``.
        extra: the extra columns in order.
    """

    def __init__(self, joint_names: Sequence[str], extra: Sequence[str]) -> None:
        self.joints = {j: i for i, j in enumerate(joint_names)}
        self.extra = {c: i for i, c in enumerate(extra)}
        self.nv = len(self.joints)
        self.size = 3 * self.nv + len(self.extra)

    def __call__(self, kind: str, key: str) -> int:
        """Index of column ``(kind, key)``."""
        if kind == "extra":
            return 3 * self.nv + self.extra[key]
        return {"q": 0, "qd": 1, "qdd": 2}[kind] * self.nv + self.joints[key]


def recorded_identity(meta: Mapping[str, Any]) -> RobotIdentity | None:
    """The robot identity a graph records (None for graphs of earlier versions)."""
    data = meta.get(Key.ROBOT_IDENTITY)
    if not data:
        return None
    return RobotIdentity.from_json(data)
