"""Run an exported contact estimator with numpy only: ONNX graphs or a C step library.

:func:`torchcontact.export.export_estimator` (``python -m export estimator ...``) writes two graphs
of one robot, sensor set and slot layout, with the same ``metadata_props``:

* ``<name>.onnx``, the **batched** graph: named inputs ``(N, ...)``, one node per scalar operation
  of the estimator program, each running over the ``N`` frames (throughput, :meth:`run`);
* ``<name>.step.onnx``, the **single-frame** graph: one packed input vector and one packed output
  vector (layouts in the metadata), every stage vectorised over bodies and slots, a few hundred
  nodes (latency, :meth:`step`).

``export estimator --format c`` writes the single-frame estimator as a C library instead
(:mod:`torchcontact.online.cstep`): :class:`EstimatorRuntime` runs it with ``backend="c"``
(ctypes; no onnxruntime), with the same inputs and outputs (:mod:`torchcontact.onnx.backends`).

Both take the raw reading when a residual correction is chained into them (``--residual`` at
export), or :class:`EstimatorRuntime` chains a separate correction graph (``residual=``); either
way one call goes from the raw reading to the estimate. :class:`ResidualGraph` is the one place
that knows the correction graphs' interfaces.

A step with online inputs (a C library; a graph exported with ``online``) also tracks each
sensor's offset against the model while no contact is active (``track_bias``), and takes
:meth:`EstimatorRuntime.tare`, :meth:`~EstimatorRuntime.set_payload` and
:meth:`~EstimatorRuntime.identify_payload` (:mod:`torchcontact.onnx.tracking`, on the one
:class:`~torchcontact.online.state.OnlineState`); each step then returns the bias state.

:meth:`EstimatorRuntime.step` and :meth:`EstimatorRuntime.run` take one :class:`Inputs` value
(or a mapping) holding the inputs by their names (:data:`torchcontact.onnx.format.INPUTS`; the
older spellings are accepted); a new input of a graph is one more name, not one more parameter.
This module imports neither torch nor, for a C step, onnxruntime.

Example:
    >>> rt = EstimatorRuntime("tcarm.onnx", robot="tcarm")  # doctest: +SKIP
    >>> out = rt.step(Inputs(q=q, qd=qd, qdd=qdd, ft=ft, positions=p))  # doctest: +SKIP
    >>> out["force"].shape  # (K, 3), N, in each slot's link frame  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.errors import InputError, ModelMismatchError
from torchcontact.online.bias import BiasState, BiasTracker
from torchcontact.online.payload import Payload
from torchcontact.onnx import format as fmt
from torchcontact.onnx.backends import (
    LIBRARY_SUFFIXES,
    CStep,
    OnnxStep,
    metadata_of,
    open_session,
    session_options,
)
from torchcontact.onnx.checks import check_file, identity_of, robot_identity
from torchcontact.onnx.format import ESTIMATOR_FORMAT, RESIDUAL_FORMATS, Key
from torchcontact.onnx.residuals import ResidualGraph
from torchcontact.onnx.tracking import StepOnline

__all__ = [
    "EstimatorRuntime",
    "Inputs",
    "ModelMismatchError",
    "ResidualGraph",
    "identity_of",
    "robot_identity",
    "session_options",
]

#: Format of the estimator graphs this runtime reads (``metadata_props["format"]``).
FORMAT = ESTIMATOR_FORMAT
#: Formats of the residual-correction graphs it chains (re-exported by torchcontact.runtime).
RESIDUAL_FORMATS = RESIDUAL_FORMATS
#: The positional order of :meth:`EstimatorRuntime.step` and ``run`` of earlier versions.
_POSITIONAL = ("q", "qd", "qdd", "ft", "positions", "active", "directions", "wrenches",
               "ft_residual")  # fmt: skip


@dataclass
class Inputs:
    """The inputs of one frame (:meth:`EstimatorRuntime.step`) or of ``N`` (``run``), by name.

    Every field is optional here; the graph says which it needs (a missing required one is an
    :class:`~torchcontact.errors.InputError` naming it), the others default to zeros
    (``active`` and ``pushing`` to ones, ``tau_mask`` to the finite entries of
    ``tau_measured``). Shapes per frame (``run`` adds a leading ``N``); names, units and frames in
    :data:`torchcontact.onnx.format.INPUTS`.

    Attributes:
        q: ``(nv,)`` joint positions, rad or m. ``qd``, ``qdd`` likewise.
        ft: ``(S, 6)`` raw readings ``[N; N m]``, or sensor name -> ``(6,)``.
        positions: ``(K, 3)`` contact points, link frames, m.
        active: ``(K,)`` 1/0 slot activity.
        directions: ``(K, 3)`` force directions of ``force_dir`` slots.
        wrenches: ``(K, 6)`` wrenches of ``known`` slots.
        ft_residual: ``(S, 6)`` a further correction subtracted from ``ft``.
        omega: ``(3,)`` base angular velocity, rad/s (moving base); ``domega``, ``proper_acc``.
        tau_measured: ``(nv,)`` measured joint torques (torque rows); ``tau_mask`` ``(nv,)``.
        ft_cov: ``(S, 6, 6)`` reading noise covariances (covariance).
        normals: ``(K, 3)``, ``friction`` ``(K,)``, ``pushing`` ``(K,)`` (constrained graphs).
        extra: column name -> value, the extra columns chained corrections read.
        h_in: sensor -> ``(N, L, H)`` recurrent states of corrections inside the graph (``run``).
    """

    q: Any = None
    qd: Any = None
    qdd: Any = None
    ft: Any = None
    positions: Any = None
    active: Any = None
    directions: Any = None
    wrenches: Any = None
    ft_residual: Any = None
    omega: Any = None
    domega: Any = None
    proper_acc: Any = None
    tau_measured: Any = None
    tau_mask: Any = None
    ft_cov: Any = None
    normals: Any = None
    friction: Any = None
    pushing: Any = None
    extra: Mapping[str, Any] | None = None
    h_in: Mapping[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        """The given fields (None left out)."""
        return {
            f.name: v for f in dataclasses.fields(self) if (v := getattr(self, f.name)) is not None
        }


_FIELDS = frozenset(f.name for f in dataclasses.fields(Inputs))
#: Inputs a graph may not read (its layout has no slot of that kind), silently unused then.
_SLOT_DATA = frozenset(("directions", "wrenches", "extra"))
#: How :meth:`EstimatorRuntime.step` fills a field of the packed input.
_PLAIN, _FT, _MASK, _EXTRA, _STATE = range(5)
#: How :meth:`EstimatorRuntime.step` reads a field of the packed output.
_VIEW, _FM, _INT, _STATUS, _TAU, _LOCSTATUS = range(6)
#: The outputs every step returns (``fm`` of the ONNX step holds ``force`` and ``moment``),
#: and a step exported with ``localize`` the localization's.
_OUTPUTS = frozenset(("force", "moment", "joint_torques", "rank", "unknowns", "residual",
                      "status", "covariance", "localize_status", "localize_position"))  # fmt: skip


def _given(inputs: Any, args: tuple, named: Mapping[str, Any]) -> dict[str, Any]:
    """One dict of inputs (an :class:`Inputs`, a mapping, or old-style args), as given.

    Names are not checked here (:func:`_named` does, when a name is not a graph's); a dict is
    returned as it is (never modified).

    Raises:
        InputError: too many positional values.
    """
    if not args:
        if type(inputs) is dict and not named:
            return inputs  # the common case
        if isinstance(inputs, Inputs):
            return {**inputs.as_dict(), **named}
        if isinstance(inputs, Mapping):
            return {**inputs, **named}
    # q, qd, qdd, ft, positions, ... as earlier versions took them
    args = args if inputs is None else (inputs, *args)
    if len(args) > len(_POSITIONAL):
        raise InputError(f"at most {len(_POSITIONAL)} positional inputs {_POSITIONAL}")
    given = dict(zip(_POSITIONAL, args, strict=False))
    given.update(named)
    return given


def _named(given: Mapping[str, Any]) -> dict[str, Any]:
    """``given`` by the one name of each input, the None values left out.

    Raises:
        InputError: an unknown input name.
    """
    out = {}
    for k, v in given.items():
        c = fmt.canonical(k)
        if c not in _FIELDS:
            raise InputError(f"unknown input {k!r}; the inputs are {sorted(_FIELDS)}")
        if v is not None:
            out[c] = v
    return out


class EstimatorRuntime:
    """An exported contact estimator, loaded for inference: an ONNX graph or a C step library.

    Args:
        path: the batched graph ``<name>.onnx`` (or the single-frame ``<name>.step.onnx``) written
            by :func:`torchcontact.export.export_estimator`, the other one found beside it; or a
            C step library ``NAME.so`` (``export estimator --format c``).
        robot: the robot the caller runs (a URDF path, ``"tcarm"``, or a ``RobotModel``): the
            file is refused unless it was exported for this robot (the robot identity it
            records, :mod:`torchcontact.identity`; files of earlier versions: the URDF text's
            sha256), and with a model its joint names.
        backend: ``"onnx"`` (onnxruntime) or ``"c"`` (the C library through ctypes; no
            onnxruntime needed); default: ``"c"`` for a ``.so``/``.dylib``/``.dll`` file.
        residual: a residual-correction graph (:class:`ResidualGraph`) to chain before the
            estimator, or a list of them (one per sensor); not with a graph that already holds
            its correction. With a C step: its learned layer (the library holds the offset and
            inertial layers).
        expect_robot_sha256: refuse the file unless its URDF hash (or identity hash) matches.
        expect_joint_names: refuse the file unless its joint order matches.
        expect_sensors: refuse the file unless its F/T sensor names (in order) match.
        expect_slots: refuse the file unless its ``(links, kinds)`` slot layout matches.
        intra_op_threads: onnxruntime threads (1: the lowest single-frame latency).
        step_graph: load the single-frame graph for :meth:`step` (False: :meth:`step` runs the
            batched graph with ``N = 1``).
        track_bias: track each sensor's offset against the model on contact-free frames
            (:mod:`torchcontact.online.bias`): True (with ``tracker_options``), a
            :class:`~torchcontact.online.bias.BiasTracker`, or False (the offsets change only
            by :meth:`tare` and :meth:`identify_payload`). Needs a step with online inputs: a C
            step, or an ONNX graph exported with ``online`` (``--online``).
        tracker_options: :class:`~torchcontact.online.bias.BiasTracker` keyword arguments
            (``time_constant`` s, ``period`` s, ``ft_std``, ``gate``, ...).
        prefix: the C library's symbol prefix (``--prefix`` at export).

    Attributes:
        metadata: the file's metadata (``metadata_props`` of the graphs, JSON values decoded;
            the C library's JSON).
        kind: ``"onnx"`` or ``"c"``.
        backend: the single-frame step (:class:`~torchcontact.onnx.backends.OnnxStep` or
            :class:`~torchcontact.onnx.backends.CStep`), None without one.
        online: its :class:`~torchcontact.onnx.tracking.StepOnline` (offsets, payloads), None
            when the step has no online inputs.
        nv, S, K: joints, sensors, contact slots.
        joint_names, sensor_names, slot_links, slot_kinds: the layout.
        dtype: numpy dtype of the inputs and outputs.
        extra: names of the extra input columns the chained corrections read.

    Raises:
        InputError: no such file, an unknown backend, ``track_bias`` on a step without online
            inputs, bad tracker options.
        ModelMismatchError: the file is not an estimator of this format, or a check fails.

    Example:
        >>> rt = EstimatorRuntime("arm.so", robot="tcarm", track_bias=True)  # doctest: +SKIP
        >>> out = rt.step({"q": q, "qd": qd, "qdd": qdd, "ft": ft})  # doctest: +SKIP
        >>> out["force"], out["bias"].offset  # (K, 3) N; (S, 6) tracked offsets  # doctest: +SKIP
    """

    def __init__(
        self,
        path: str | os.PathLike,
        robot: Any = None,
        *,
        backend: str | None = None,
        residual: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
        expect_robot_sha256: str | None = None,
        expect_joint_names: Sequence[str] | None = None,
        expect_sensors: Sequence[str] | None = None,
        expect_slots: tuple[Sequence[str], Sequence[str]] | None = None,
        intra_op_threads: int = 1,
        step_graph: bool = True,
        track_bias: bool | BiasTracker = False,
        tracker_options: Mapping[str, Any] | None = None,
        prefix: str = "tc_estimator",
    ) -> None:
        path = Path(os.fspath(path))
        if not path.is_file():
            raise InputError(f"{path}: no such file")
        kind = backend or ("c" if path.suffix in LIBRARY_SUFFIXES else "onnx")
        if kind not in ("onnx", "c"):
            raise InputError(f"backend must be 'onnx' or 'c', got {backend!r}")
        self.kind, self.path = kind, str(path)
        self._intra = intra_op_threads
        self._batched: Any = None
        self._batched_path: Path | None = None
        self.step_session: Any = None
        self.backend: OnnxStep | CStep | None = None
        if kind == "c":
            self.backend = CStep(path, prefix)
            meta = self.backend.metadata
        else:
            meta = self._open_onnx(path, step_graph)
        self.metadata = meta
        self.joint_names = tuple(meta[Key.JOINT_NAMES])
        self.sensor_names = tuple(s["name"] for s in meta[Key.SENSORS])
        self.slot_links, self.slot_kinds = tuple(meta[Key.SLOT_LINKS]), tuple(meta[Key.SLOT_KINDS])
        self.nv, self.S, self.K = (
            len(self.joint_names),
            len(self.sensor_names),
            len(self.slot_links),
        )
        self.dtype = np.dtype(meta[Key.DTYPE])
        check_file(self.path, meta, robot, expect_robot_sha256, expect_joint_names,
                   expect_sensors, expect_slots)  # fmt: skip
        if kind == "onnx" and self.step_session is not None:
            self.backend = OnnxStep(self.step_session, meta[Key.STEP_INPUTS],
                                    meta[Key.STEP_OUTPUTS], self.dtype)  # fmt: skip
        # chained corrections: inside the graphs (export --residual) or run here
        self.residuals: list[ResidualGraph] = []
        inside = list(meta.get(Key.RESIDUALS, []))
        if residual is not None:
            if inside:
                raise ModelMismatchError(
                    f"{path} already holds residual corrections for {[r['sensor'] for r in inside]}"
                )
            paths = [residual] if isinstance(residual, (str, os.PathLike)) else list(residual)
            for p in paths:
                rg = ResidualGraph.load(p, intra_op_threads)
                rg.check(self.joint_names, self.sensor_names, meta)
                self.residuals.append(rg)
            extra = [c for rg in self.residuals for c in rg.extra]
        else:
            extra = [c for r in inside for c in r["extra"]]
        self.extra = tuple(dict.fromkeys(extra))
        self._inside = inside
        self._state: dict[str, np.ndarray] = {}
        self.reset()
        self._setup_step()
        # offsets and payloads: every step with online inputs (C libraries, --online graphs)
        self.online: StepOnline | None = None
        if self.backend is not None and meta.get(Key.ONLINE) and "bias" in self._xv:
            self.online = StepOnline(meta, self._xv, self.backend.outputs,
                                     write_defaults=kind == "onnx", track_bias=track_bias,
                                     tracker_options=tracker_options)  # fmt: skip
        elif track_bias is not False:
            raise InputError(
                f"{path} has no online inputs (bias, theta): bias tracking needs a C step or a"
                " graph exported with --online"
            )

    def _open_onnx(self, path: Path, step_graph: bool) -> dict[str, Any]:
        """Open the ONNX graphs (the step graph first); returns their metadata."""
        self._so = session_options(self._intra)
        # open the small single-frame graph first when it lies beside the batched one: the
        # batched graph (thousands of nodes, seconds to optimise) loads on the first run()
        step_file = path.with_name(f"{path.name.removesuffix('.onnx')}.step.onnx")
        if step_graph and not path.name.endswith(".step.onnx") and step_file.is_file():
            first = open_session(step_file, self._so)
            if metadata_of(first).get(Key.BATCHED_GRAPH) != path.name:
                first = open_session(path, self._so)
        else:
            first = open_session(path, self._so)
        meta = metadata_of(first)
        if meta.get(Key.FORMAT) != FORMAT:
            raise ModelMismatchError(
                f"{path} is not a torchcontact estimator graph of format {FORMAT!r} (found"
                f" {meta.get('format')!r}): re-export it with python -m export estimator"
            )
        graph = meta.get(Key.GRAPH)
        self._batched = first if graph == "batched" else None
        self._batched_path = path.parent / str(meta.get(Key.BATCHED_GRAPH))
        self.step_session = first if graph == "step" else None
        other = path.parent / str(meta.get(Key.STEP_GRAPH))
        if graph == "batched" and step_graph and meta.get(Key.STEP_GRAPH) and other.is_file():
            self.step_session = open_session(other, self._so)
            smeta = metadata_of(self.step_session)
            if {k: v for k, v in smeta.items() if k != "graph"} != {
                k: v for k, v in meta.items() if k != "graph"
            }:
                raise ModelMismatchError(
                    f"{other} is not the single-frame graph of {path} (re-export both)"
                )
        return meta

    # ------------------------------------------------------------------------------- checks

    @property
    def input_names(self) -> frozenset[str]:
        """The input names :meth:`step` takes (the file's inputs and those it may leave unused)."""
        return self._accepts

    @property
    def ft_noise(self) -> dict[str, tuple[float, ...]] | None:
        """Per sensor the 6 standard deviations ``[N; N m]`` the solve is weighted by.

        Fixed at export (``export estimator --ft-noise``, metadata ``ft_noise``); None: the
        file solves the paper's unweighted ``pinv(A) b``.
        """
        noise = self.metadata.get(Key.FT_NOISE)
        if not noise:
            return None
        return {s: tuple(float(v) for v in n["std"]) for s, n in noise["sensors"].items()}

    def __repr__(self) -> str:
        noise = self.ft_noise
        weighting = "unweighted" if noise is None else f"weighted by ft_noise {noise}"
        return (
            f"EstimatorRuntime({self.path!r}, robot={self.metadata['robot']!r}, nv={self.nv},"
            f" sensors={list(self.sensor_names)}, slots={list(self.slot_kinds)},"
            f" dtype={self.dtype}, backend={self.kind!r}, {weighting})"
        )

    def reset(self) -> None:
        """Zero the recurrent state of the chained corrections (a new time series starts)."""
        self._state = {}
        for rg in self.residuals:
            if rg.state_shape is not None:
                self._state[rg.path] = np.zeros((1, *rg.state_shape), rg.dtype)
        for r in self._inside:
            if r.get("state_shape"):
                self._state[r["sensor"]] = np.zeros(tuple(r["state_shape"]), self.dtype)

    # ---------------------------------------------------------------------------- single frame

    def _setup_step(self) -> None:
        bk = self.backend
        self._xv: dict[str, np.ndarray] = {}
        self._accepts: frozenset[str] = frozenset()
        if bk is None:
            self._x = None
            return
        self._x = bk.x
        self._xv = {k: bk.x[o : o + int(np.prod(sh))].reshape(sh) for k, (o, sh) in
                    bk.inputs.items()}  # fmt: skip
        self._fresh: set[str] = set()
        # per field of the packed input: how step() fills it, and its default (None: required;
        # ones for the activity flags; zeros for the rest); the online inputs are the
        # StepOnline's
        defaults = {k: None for k in fmt.REQUIRED} | {k: 1.0 for k in fmt.ONES}
        special = {"ft": _FT, "tau_mask": _MASK, fmt.EXTRA: _EXTRA}
        self._fill = [
            (k, v, _STATE if k.startswith("h_in.") else special.get(k, _PLAIN),
             defaults.get(k, 0.0))
            for k, v in self._xv.items() if k != "bias" and not k.startswith("theta.")
        ]  # fmt: skip
        # ft_residual is subtracted here when the step has no such input (C steps)
        self._residual_in = "ft_residual" in self._xv
        self._accepts = frozenset(k for k, *_ in self._fill) | _SLOT_DATA | {"ft_residual"}
        # the output fields, as (start, stop, shape)
        self._out = {k: (o, o + int(np.prod(sh)), sh) for k, (o, sh) in bk.outputs.items()}
        self._reused = bk.kind == "c"  # the library writes into one buffer: copy what we return
        tj = list(self.metadata.get(Key.TORQUE_JOINTS) or self.joint_names)
        n_tau = self._out["joint_torques"][2][0]
        self._tau_idx = (
            None if n_tau == self.nv else np.array([self.joint_names.index(j) for j in tj])
        )
        # how _decode reads each output field
        kinds = {"fm": _FM, "rank": _INT, "unknowns": _INT, "status": _STATUS,
                 "joint_torques": _VIEW if self._tau_idx is None else _TAU,
                 "localize_status": _LOCSTATUS}  # fmt: skip
        self._plan = [(k, a, b, sh, kinds.get(k, _VIEW)) for k, (a, b, sh) in self._out.items()
                      if k in _OUTPUTS or k == "fm"]  # fmt: skip
        # a step with localization: the sensor whose region a localized contact lies in (not
        # contact-free for the bias tracker)
        loc = self.metadata.get(Key.LOCALIZE)
        self._loc_region = loc.get("region") if isinstance(loc, dict) else None

    def _put(self, name: str, view: np.ndarray, value: Any, default: float | None) -> None:
        """Write one input field of the packed vector (``default`` when ``value`` is None)."""
        if value is None:
            if default is None:
                raise InputError(f"{name} is required by this graph, shape {view.shape}")
            if name not in self._fresh:
                view[...] = default
                self._fresh.add(name)
            return
        self._fresh.discard(name)
        if type(value) is np.ndarray and value.shape == view.shape:
            view[...] = value
            return
        arr = np.asarray(value)
        if arr.shape != view.shape:
            if (
                arr.size == view.size
                and arr.ndim <= 1 + view.ndim
                and arr.squeeze().shape == view.squeeze().shape
            ):
                arr = arr.reshape(view.shape)
            else:
                raise InputError(f"{name} must have shape {view.shape}, got {arr.shape}")
        view[...] = arr

    def step(self, inputs: Inputs | Mapping[str, Any] | None = None, /, *args: Any,
             contact_free: Any = None, t: float | None = None,
             **named: Any) -> dict[str, Any]:  # fmt: skip
        """Estimate one frame from the raw readings (and update the offsets, on an online step).

        Args:
            inputs: an :class:`Inputs` or a mapping name -> value (one frame's shapes, see
                :class:`Inputs`; the older spellings of :data:`~torchcontact.onnx.format.INPUTS`
                are accepted). Earlier versions' form ``step(q, qd, qdd, ft, positions, active,
                directions, wrenches, ft_residual, **keywords)`` is accepted too.
            *args: the positional values of that earlier form.
            contact_free: the caller's contact-free signal for the bias tracker (bool, or
                ``(S,)`` per sensor: a contact localizer, a user's switch); a sensor is updated
                only when no active slot lies in its region and this does not say otherwise
                (:meth:`~torchcontact.online.state.OnlineState.contact_free`).
            t: the frame's time, s (the tracker's clock; None: one nominal period on).
            **named: inputs by name (added to ``inputs``).

        Returns:
            ``force``, ``moment`` ``(K, 3)`` (N, N m; link frames, moment about the point),
            ``joint_torques (nv,)`` (NaN for joints the file was exported without),
            ``rank``, ``unknowns`` ``(S,)`` int64, ``residual (S,)``, ``status`` (int, 0 ok;
            bits of :class:`torchcontact.Status`; the outputs are NaN otherwise), ``covariance
            (K, 6, 6)`` when exported with it, and a constrained graph's ``converged``,
            ``iterations`` ``(S,)`` and ``cone_active (K,)``. A step with online inputs adds
            ``ft_model (S, 6)`` (the contact-free reading the model predicts, every correction
            but the offset) and ``bias``, the
            :class:`~torchcontact.online.bias.BiasState` after the frame (offsets, their
            uncertainty, time since the last update). A step exported with ``localize``
            (``--localize LINK``) adds ``localize_status`` (int, bits of
            :class:`~torchcontact.status.LocalizeStatus`; -1 where ``status`` is not 0) and
            ``localize_position (3,)`` (the contact point LINK's slot was given, link frame,
            m; NaN where the localization was not used).

        Raises:
            InputError: a wrong shape, an unknown input, a missing required input or extra
                column.
        """
        if type(inputs) is dict and not args and not named:
            given = inputs  # the common case
        else:
            given = _given(inputs, args, named)
        accepted = given.keys() <= self._accepts
        if self._x is None or not accepted:
            given = _named(given)  # old spellings, None for absent
            accepted = given.keys() <= self._accepts
        if self._x is None:  # the batched graph with N = 1
            one = {k: (np.asarray(v)[None] if k not in ("extra", "h_in") else v)
                   for k, v in given.items()}  # fmt: skip
            if "ft" in given:
                one["ft"] = np.asarray(self._ft_array(given["ft"]), np.float64).reshape(
                    1, self.S, 6
                )
            if "extra" in given:
                one["extra"] = {k: np.atleast_1d(v) for k, v in given["extra"].items()}
            out = self.run(one)
            return {k: (v[0] if k != "status" else int(v[0])) for k, v in out.items()}
        if "ft" not in given:
            raise InputError(f"ft is required by this graph, shape {self._xv['ft'].shape}")
        raw = ft = given["ft"]
        if type(ft) is not np.ndarray:
            raw = ft = self._ft_array(ft)
        extra = given.get("extra")
        if not accepted:
            # a layout without force_dir (known) slots does not read directions (wrenches)
            bad = sorted(given.keys() - self._accepts)
            raise InputError(f"this graph has no input {bad[0]!r} (exported without it)")
        if self.residuals:
            ft = ft - self._correct(given.get("q"), given.get("qd"), given.get("qdd"), extra,
                                    batch=False)  # fmt: skip
        fres = given.get("ft_residual")
        if fres is not None and not self._residual_in:  # a step without the input: here
            ft = ft - np.asarray(fres, np.float64).reshape(np.shape(ft))
            fres = None
        put = self._put
        for name, view, kind, default in self._fill:  # the packed input's fields, in order
            if kind == _PLAIN:
                put(name, view, given.get(name), default)
            elif kind == _FT:
                put(name, view, ft, None)
            elif kind == _MASK:
                value = given.get(name)
                if value is None and given.get("tau_measured") is not None:
                    value = np.isfinite(np.asarray(given["tau_measured"], dtype=float))
                put(name, view, value, default)
            elif kind == _EXTRA:
                vals = extra or {}
                missing = [c for c in self.extra if c not in vals]
                if missing:
                    raise InputError(f"extra inputs {missing} are required by the corrections")
                view[...] = [vals[c] for c in self.extra]
            else:  # a recurrent correction's state, carried from the previous step
                view[...] = self._state[name[5:]]
        onl = self.online
        if onl is not None:
            onl.before()
        out = self.backend.call()  # type: ignore[union-attr]
        if self._reused:
            out = out.copy()
        res = self._decode(out)
        if onl is not None:  # the offsets learn from the reading the step was given
            net = ft
            if not (type(ft) is np.ndarray and ft.dtype == np.float64 and ft.shape == (self.S, 6)):
                net = np.asarray(ft, np.float64).reshape(self.S, 6)
            if fres is not None:
                net = net - np.asarray(fres, np.float64).reshape(self.S, 6)
            if self._loc_region is not None and res.get("localize_status") == 0:
                # the localized contact is a contact: its region is not contact-free
                free = np.ones(self.S, bool) if contact_free is None else contact_free
                free = np.array(np.broadcast_to(np.asarray(free, bool).reshape(-1), (self.S,)))
                free[self._loc_region] = False
                contact_free = free
            ft_model, res["bias"] = onl.after(out, net, res["status"], contact_free, t)
            if self.residuals or given.get("ft_residual") is not None:
                # corrections made outside the step's model are part of the model's reading
                ft_model += np.asarray(raw, np.float64).reshape(self.S, 6) - net
            res["ft_model"] = ft_model
        return res

    def _decode(self, out: np.ndarray) -> dict[str, Any]:
        """The outputs of the packed output ``out`` (views into it; the plan of ``_setup_step``)."""
        res: dict[str, Any] = {}
        for name, a, b, sh, kind in self._plan:
            v = out[a:b]
            if kind == _VIEW:
                res[name] = v.reshape(sh)
            elif kind == _FM:  # the ONNX step: [force, moment, ...] per slot
                fm = v.reshape(sh)
                res["force"], res["moment"] = fm[:, 0:3], fm[:, 3:6]
            elif kind == _INT:
                res[name] = v.astype(np.int64)
            elif kind == _STATUS:
                res[name] = int(v[0])
            elif kind == _LOCSTATUS:  # NaN where the step's status is not 0: -1
                res[name] = int(v[0]) if v[0] == v[0] else -1
            else:  # only some joints' torques: the others are NaN
                full = np.full(self.nv, np.nan, out.dtype)
                full[self._tau_idx] = v
                res[name] = full
        for r in self._inside:
            if r.get("state_shape"):
                self._state[r["sensor"]] = self._field(out, fmt.state_out(r["sensor"])).copy()
        return res

    def _field(self, out: np.ndarray, name: str) -> np.ndarray:
        a, b, sh = self._out[name]
        return out[a:b].reshape(sh)

    def _ft_array(self, ft: Any) -> np.ndarray:
        if isinstance(ft, Mapping):
            missing = [s for s in self.sensor_names if s not in ft]
            if missing:
                raise InputError(f"ft is missing readings of sensors {missing}")
            return np.stack(
                [np.asarray(ft[s], dtype=np.float64).reshape(6) for s in self.sensor_names]
            )
        return np.asarray(ft)

    def _correct(self, q, qd, qdd, extra, batch: bool) -> np.ndarray:
        """Corrections of the separately chained residual graphs, ``(S, 6)`` or ``(N, S, 6)``."""
        q2 = np.atleast_2d(np.asarray(q, dtype=np.float64))
        n = q2.shape[0]
        qd2 = np.asarray(qd, dtype=np.float64).reshape(n, -1)
        qdd2 = np.asarray(qdd, dtype=np.float64).reshape(n, -1)
        ex = {k: np.asarray(v, dtype=np.float64).reshape(n) for k, v in (extra or {}).items()}
        corr = np.zeros((n, self.S, 6))
        for rg in self.residuals:
            state = None
            if rg.state_shape is not None:
                state = self._state[rg.path]
                if state.shape[0] != n:
                    state = np.zeros((n, *rg.state_shape), rg.dtype)
            outs = rg.session.run(None, rg.feed(self.joint_names, q2, qd2, qdd2, ex, state))
            corr[:, self.sensor_names.index(rg.sensor)] += outs[0]
            if rg.state_shape is not None and not batch:
                self._state[rg.path] = outs[1]
        return corr if batch else corr[0]

    # ----------------------------------------------------------------------------------- batch

    def _batched_session(self) -> Any:
        if self._batched is None:
            if self._batched_path is None or not self._batched_path.is_file():
                raise ModelMismatchError(f"the batched graph {self._batched_path} is missing")
            self._batched = open_session(self._batched_path, self._so)
        return self._batched

    def run(self, inputs: Inputs | Mapping[str, Any] | None = None, /, *args: Any,
            chunk_size: int = 16384, **named: Any) -> dict[str, np.ndarray]:  # fmt: skip
        """Estimate ``N`` independent frames (the batched graph; a C step: its ``run``).

        Args:
            inputs: an :class:`Inputs` or a mapping name -> value, each with a leading ``N``
                (``ft`` ``(N, S, 6)``, ``extra`` column -> ``(N,)``, ``h_in`` sensor ->
                ``(N, L, H)`` recurrent states of corrections inside the graph, default zeros,
                each row an independent frame). The earlier form ``run(q, qd, qdd, ft, ...)``
                is accepted too.
            *args: the positional values of that earlier form.
            chunk_size: frames per graph call (bounds memory, keeps the working set in cache).
            **named: inputs by name (added to ``inputs``).

        Returns:
            As :meth:`step` with a leading ``N``; ``status`` ``(N,)`` int64. No online state is
            updated; a C step uses the current offsets and payloads, an ONNX batched graph the
            correction stack's (``ft_model``, ``bias`` are not returned).

        Raises:
            InputError: a wrong shape, an unknown input or a missing required input.
        """
        given = dict(_given(inputs, args, named))
        if self.kind == "c":
            return self._run_c(_named(given))
        sess = self._batched_session()
        if "q" not in given:
            raise InputError("q is required by this graph, shape (N, nv)")
        n = int(np.shape(given["q"])[0])
        extra, h_in = given.pop("extra", None), given.pop("h_in", None)
        if self.residuals and "ft" in given:
            corr = self._correct(given.get("q"), given.get("qd"), given.get("qdd"), extra, True)
            given["ft"] = np.asarray(given["ft"], dtype=np.float64) - corr
        inputs_ = {i.name for i in sess.get_inputs()}
        unknown = [k for k in given if k not in inputs_]
        if unknown:
            raise InputError(f"this graph has no inputs {unknown} (exported without them)")
        if "tau_measured" in given and "tau_mask" not in given:
            given["tau_mask"] = np.isfinite(np.asarray(given["tau_measured"], dtype=float))
        feed = {}
        for i in sess.get_inputs():
            trailing = tuple(int(d) for d in i.shape[1:])
            name = i.name
            if name == fmt.EXTRA:
                vals = extra or {}
                missing = [c for c in self.extra if c not in vals]
                if missing:
                    raise InputError(f"extra inputs {missing} are required by the corrections")
                x = (
                    np.stack([np.asarray(vals[c], dtype=float).reshape(n) for c in self.extra], -1)
                    if self.extra
                    else np.zeros((n, 0))
                )
            elif name.startswith("h_in."):
                x = (h_in or {}).get(name[5:])
                if x is None:
                    x = np.zeros((n, *trailing))
            else:
                x = given.get(name)
                if x is None:
                    if name in fmt.REQUIRED:
                        raise InputError(
                            f"{name} is required by this graph, shape (N, "
                            f"{', '.join(map(str, trailing))})"
                        )
                    x = (np.ones if name in fmt.ONES else np.zeros)((n, *trailing))
            x = np.asarray(x, dtype=self.dtype)
            if x.shape != (n, *trailing):
                raise InputError(
                    f"{name} must have shape ({n}, {', '.join(map(str, trailing))}), got {x.shape}"
                )
            feed[name] = x
        names = [o.name for o in sess.get_outputs()]
        parts = [
            sess.run(None, {k: v[s : s + chunk_size] for k, v in feed.items()})
            for s in range(0, max(n, 1), chunk_size)
        ]
        return {
            k: np.concatenate([p[i] for p in parts]) if len(parts) > 1 else parts[0][i]
            for i, k in enumerate(names)
        }

    def _run_c(self, given: dict[str, Any]) -> dict[str, np.ndarray]:
        """:meth:`run` on a C step: the frames packed as rows, one library call."""
        bk = self.backend
        assert isinstance(bk, CStep)
        if "q" not in given:
            raise InputError("q is required by this library, shape (N, nv)")
        n = int(np.shape(given["q"])[0])
        extra, fres = given.pop("extra", None), given.pop("ft_residual", None)
        given.pop("h_in", None)
        missing = [k for k in fmt.REQUIRED if k in bk.inputs and given.get(k) is None]
        if missing:
            raise InputError(f"{missing[0]} is required by this library")
        unknown = [k for k in given if k not in bk.inputs or k == "bias" or k.startswith("theta")]
        if unknown:
            raise InputError(f"this library has no inputs {unknown} (exported without them)")
        ft = np.asarray(self._ft_array(given["ft"]) if isinstance(given["ft"], Mapping)
                        else given["ft"], dtype=np.float64).reshape(n, self.S, 6)  # fmt: skip
        if self.residuals:
            ft = ft - self._correct(given.get("q"), given.get("qd"), given.get("qdd"), extra, True)
        if fres is not None:
            ft = ft - np.asarray(fres, np.float64).reshape(n, self.S, 6)
        given["ft"] = ft
        if "tau_measured" in given and "tau_mask" not in given:
            given["tau_mask"] = np.isfinite(np.asarray(given["tau_measured"], dtype=float))
        if "active" in bk.inputs and "active" not in given:
            given["active"] = np.ones((n, self.K))
        if self.online is not None:
            self.online.before()
        base = bk.x0.copy()  # the library's defaults, with the current offsets and payloads
        for k, (o, sh) in bk.inputs.items():
            if k == "bias" or k.startswith("theta."):
                base[o : o + int(np.prod(sh))] = bk.x[o : o + int(np.prod(sh))]
        out = bk.run(bk.pack(n, base, **given))
        res: dict[str, np.ndarray] = {}
        for k, (a, b, sh) in self._out.items():
            res[k] = out[:, a:b].reshape(n, *sh)
        if self._tau_idx is not None:
            tau = np.full((n, self.nv), np.nan, out.dtype)
            tau[:, self._tau_idx] = res["joint_torques"]
            res["joint_torques"] = tau
        res["rank"], res["unknowns"] = (
            res["rank"].astype(np.int64),
            res["unknowns"].astype(np.int64),
        )
        res["status"] = res["status"].reshape(n).astype(np.int64)
        for k in [k for k in res if k.startswith("regressor.")]:
            del res[k]
        return res

    # ---------------------------------------------------------------------- offsets, payloads

    def _online(self) -> StepOnline:
        if self.online is None:
            raise InputError(
                f"{self.path} has no online inputs (bias, theta): offsets and payloads need a C"
                " step or a graph exported with --online"
            )
        return self.online

    def tare(self, frames: int = 1) -> BiasState:
        """Re-zero the offsets now, at the current pose, from the model.

        Each offset becomes the reading less the model's prediction (the mean of the last
        ``frames`` frames), so the robot need not be in a zero pose.

        Raises:
            InputError: no frame yet, a contact active on a sensor, or a step without online
                inputs.
        """
        return self._online().tare(frames)

    def set_payload(
        self,
        mass: float | Payload | None,
        com: Any = (0.0, 0.0, 0.0),
        inertia: Any = None,
        *,
        link: str | None = None,
        sensor: str | None = None,
    ) -> Payload | None:
        """A tool change: the payload a sensor carries from the next frame on.

        Args:
            mass: kg, or a :class:`~torchcontact.online.payload.Payload`, or None (no payload).
            com: ``(3,)`` centre of mass in ``link``'s frame, m.
            inertia: ``(3, 3)`` about the centre of mass, link axes, kg m^2 (default: a point).
            link: the link it is attached to (default: the sensor's payload link, metadata
                ``online``).
            sensor: the sensor (None: the only one).

        Raises:
            InputError: a non-physical payload (mass not positive, inertia not symmetric
                positive definite or violating the triangle inequality), a link the sensor does
                not carry, a step without online inputs.
        """
        return self._online().set_payload(mass, com, inertia, link=link, sensor=sensor)

    def start_identification(self, sensor: str | None = None, **kwargs: Any) -> None:
        """Identify a sensor's payload from the next contact-free frames (a tool change).

        Its payload is cleared and its offset fitted with it; see
        :meth:`~torchcontact.online.state.OnlineState.start_identification` (``kwargs``:
        :class:`~torchcontact.online.payload.PayloadIdentifier` options).
        """
        self._online().start_identification(sensor, **kwargs)

    def identify_payload(self, sensor: str | None = None, apply: bool = True) -> Payload:
        """The payload identified so far; with ``apply`` it replaces the current one.

        Raises:
            InputError: no identification running.
            NotIdentifiableError: the data cannot identify it yet (keep moving, ask again).
        """
        return self._online().identify_payload(sensor, apply)
