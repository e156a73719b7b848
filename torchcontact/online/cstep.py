"""The C step: the single-frame estimator with its offset and inertial correction as a C library.

:func:`export_c_step` (``torchcontact export estimator --format c``) writes the generated kernel
of the whole single-frame estimator of one robot, sensor set and slot layout as a plain C-ABI
shared library, its C header and its source: no torch, no onnxruntime, no Python at run time.
The program is :func:`torchcontact.estimation.programs.estimate_program` (the same physics source
as the kernels and the ONNX graphs) with a :class:`InertialCorrection` in front:

* per sensor ``i`` the inputs ``bias.i`` ``(6,)`` (the offset subtracted from the reading: the
  correction stack's offset layer, then whatever the bias tracker says) and ``theta.i``
  ``(10 B_i,)`` (the inertial change of the ``B_i`` bodies of its subtree: the stack's inertial
  layer plus the payload, :mod:`torchcontact.online.state`), so a tool change or a tracked
  offset needs no rebuild;
* the reading the estimator uses is ``ft - bias - Y theta`` (``Y``: the sensor regressor,
  :func:`torchcontact.residual.sensor_regressor`; computed in the kernel on its own forward pass
  as the subtree's Newton-Euler wrenches of the parameter change);
* extra outputs ``ft_model`` ``(S, 6)``, the contact-free reading the model predicts with
  ``theta`` (what the bias tracker compares the raw reading with), and per sensor
  ``regressor.<sensor>`` ``(6, 10)``, the regressor of its payload body (payload identification).

The layer semantics are those of :class:`torchcontact.residual.ResidualCorrection`: the layers
correct the readings; the joint torques are those of the nominal model (as in the ONNX graphs).

Files (``--out NAME.so``): ``NAME.so`` (built with the system C++ compiler, ``-march=native``
unless told otherwise), ``NAME.h`` (the C API: packed input ``x`` and output ``out`` vectors,
``#define`` offsets of every field), ``NAME.cpp`` (the source, to build for another machine) and
``NAME.json`` (the metadata, also inside the library: ``<prefix>_metadata()``). A loader
refuses a library exported for another robot by the URDF's sha256, the identity the ONNX graphs
record (``robot_identity``; libraries of earlier versions: the URDF text's sha256), see
:class:`torchcontact.runtime.EstimatorRuntime` (``backend="c"``).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcontact import dynamics as _dyn
from torchcontact import kernels
from torchcontact import spatial as sp
from torchcontact._scalar import Scalar, add, mul, sub
from torchcontact.contacts import KINDS
from torchcontact.errors import InputError
from torchcontact.estimation import ContactEstimator
from torchcontact.estimation.layout import EstimationModel
from torchcontact.estimation.programs import estimate_program
from torchcontact.model import RobotModel
from torchcontact.online.state import payload_body, sensor_layouts

__all__ = [
    "C_FORMAT",
    "InertialCorrection",
    "export_c_step",
    "payload_body",
    "sensor_layouts",
    "stack_defaults",
    "step_program",
]

#: ``metadata["format"]`` of a C step library.
C_FORMAT = "torchcontact.cstep/1"
#: Version of the C functions' signatures.
C_ABI = 1


@dataclass(frozen=True)
class InertialCorrection:
    """Offset and inertial-parameter change subtracted from the readings, inside the program.

    Implements :class:`torchcontact.estimation.programs.ReadingCorrection`: inputs ``bias{i}``
    (6) and ``theta{i}`` (10 per subtree body), outputs ``ft_model`` (6 S) and ``regressor``
    (60 per sensor with a payload body, row-major ``(6, 10)``).

    Attributes:
        bodies: per sensor, its subtree's bodies (``theta``'s layout).
        regressor_bodies: per sensor, the body whose regressor is output (None: none).
    """

    bodies: tuple[tuple[int, ...], ...]
    regressor_bodies: tuple[int | None, ...]

    @property
    def inputs(self) -> dict[str, int]:  # noqa: D102 - see the class
        out = {f"bias{i}": 6 for i in range(len(self.bodies))}
        out.update({f"theta{i}": 10 * len(b) for i, b in enumerate(self.bodies)})
        return out

    @property
    def outputs(self) -> dict[str, int]:  # noqa: D102
        n = sum(b is not None for b in self.regressor_bodies)
        return {"ft_model": 6 * len(self.bodies), "regressor": 60 * n}

    @property
    def key(self) -> str:  # noqa: D102
        return hashlib.sha256(repr((self.bodies, self.regressor_bodies)).encode()).hexdigest()[:16]

    def apply(
        self, em: EstimationModel, x: dict, X: list, v: list, a: list, f: list, readings: list
    ) -> tuple[list, dict[str, list]]:
        """Corrected readings and ``ft_model``, ``regressor`` (see the class)."""
        tree = em.tree

        def at_sensor(reg, F: sp.Force) -> list[Scalar]:  # a child-body wrench as a reading
            Fs = sp.force_to_child(reg.T_child_sensor, F)
            return [mul(reg.sign, c) for c in (*Fs[0], *Fs[1])]

        # the model's contact-free prediction: the subtree's body wrenches summed at the sensor
        F_nom, _ = _dyn.backward_pass(tree, X, f)
        out, ft_model, regs = [], [], []
        for i, reg in enumerate(em.regions):
            theta = x[f"theta{i}"]
            fd: list = [None] * len(tree.bodies)
            for j, b in enumerate(self.bodies[i]):
                fd[b] = sp.body_wrench_link_params(
                    tree.bodies[b].Q, theta[10 * j : 10 * j + 10], v[b], a[b]
                )
            F_d, _ = _dyn.backward_pass(tree, X, fd)
            delta = at_sensor(reg, F_d[reg.child])
            nominal = at_sensor(reg, F_nom[reg.child])
            bias = x[f"bias{i}"]
            out.append(
                [sub(sub(r, o), d) for r, o, d in zip(readings[i], bias, delta, strict=True)]
            )
            ft_model += [add(n, d) for n, d in zip(nominal, delta, strict=True)]
            rb = self.regressor_bodies[i]
            if rb is None:
                continue
            # pose of the payload body in the sensor's child body, along the tree
            chain = [rb]
            while chain[-1] != reg.child:
                chain.append(tree.bodies[chain[-1]].parent)
            T: sp.Pose = (sp.EYE3, sp.ZERO3)
            for b in reversed(chain[:-1]):
                T = sp.pose_compose(T, X[b])
            cols = []
            for c in range(10):
                unit = [1.0 if k == c else 0.0 for k in range(10)]
                w = sp.body_wrench_link_params(tree.bodies[rb].Q, unit, v[rb], a[rb])
                cols.append(at_sensor(reg, sp.force_to_parent(T, w)))
            regs += [cols[c][r] for r in range(6) for c in range(10)]
        return out, {"ft_model": ft_model, "regressor": regs}


def step_program(
    em: EstimationModel,
    correction: InertialCorrection,
    coords: Sequence[int],
    flags: tuple[bool, bool, bool] = (False, False, False),
    noise: Sequence[Sequence[float]] | None = None,
) -> kernels.Program:
    """The C step's program: the estimator with the correction, torques of ``coords`` only.

    ``noise`` (per sensor 6 standard deviations, N and N m): the solve weighted by these
    constants (:func:`~torchcontact.estimation.programs.estimate_program`).
    """
    base = estimate_program(em, *flags, correction=correction, noise=noise)
    coords = tuple(int(c) for c in coords)
    outputs = dict(base.outputs)
    outputs["tau"] = len(coords)

    def fn(x: dict[str, list]) -> dict[str, list]:
        out = base.fn(x)
        out["tau"] = [out["tau"][c] for c in coords]
        return out

    return kernels.Program("cstep", fn, dict(base.inputs), outputs, f"{base.key}|tau={coords}")


# ------------------------------------------------------------------------------------ layout
#: program array -> (field name, unit) of the packed vectors (bias{i}, theta{i}, regressor
#: are split per sensor below)
_FIELDS = {
    "ft": ("ft", "[N; N m], sensor frames, raw"),
    "q": ("q", "rad or m"),
    "qd": ("qd", "rad/s or m/s"),
    "qdd": ("qdd", "rad/s^2 or m/s^2"),
    "positions": ("positions", "m, slot link frame"),
    "active": ("active", "1 in contact, 0 not"),
    "directions": ("directions", "unit, slot link frame"),
    "wrenches": ("wrenches", "[N; N m], slot link frame, about the point"),
    "omega": ("omega", "rad/s, root frame"),
    "domega": ("domega", "rad/s^2, root frame"),
    "proper_acc": ("proper_acc", "m/s^2, root frame"),
    "tau_measured": ("tau_measured", "N m or N"),
    "tau_mask": ("tau_mask", "1 measured, 0 not"),
    "ft_cov": ("ft_cov", "(N, N m)^2"),
    "force": ("force", "N, slot link frame"),
    "moment": ("moment", "N m, slot link frame, about the point"),
    "tau": ("joint_torques", "N m or N, torque_joints order"),
    "rank": ("rank", ""),
    "unknowns": ("unknowns", ""),
    "residual": ("residual", "|A x - b|"),
    "status": ("status", "bits of torchcontact.STATUS"),
    "cov": ("covariance", "per slot 6 x 6"),
    "ft_model": ("ft_model", "[N; N m], sensor frames: contact-free model reading with theta"),
}


def _layout(arrays: Mapping[str, int], S: int, K: int, nv_t: int, sensors, reg_sensors):
    """Packed layout: field -> (offset, shape, unit), and each program array's offset."""
    fields: dict[str, tuple[int, tuple[int, ...], str]] = {}
    offsets: list[int] = []
    off = 0
    shapes = {"positions": (K, 3), "directions": (K, 3), "wrenches": (K, 6), "force": (K, 3),
              "moment": (K, 3), "ft": (S, 6), "ft_cov": (S, 6, 6), "cov": (K, 6, 6),
              "ft_model": (S, 6)}  # fmt: skip
    for name, n in arrays.items():
        offsets.append(off)
        if name.startswith("bias"):
            i = int(name[4:])
            if i == 0:
                fields["bias"] = (off, (S, 6), "[N; N m], offset subtracted from ft")
        elif name.startswith("theta"):
            i = int(name[5:])
            fields[f"theta.{sensors[i]}"] = (off, (n,), "m, m c, I_origin per subtree body")
        elif name == "regressor":
            for j, s in enumerate(reg_sensors):
                fields[f"regressor.{s}"] = (off + 60 * j, (6, 10), "payload body regressor")
        else:
            label, unit = _FIELDS[name]
            fields[label] = (off, shapes.get(name, (n,)), unit)
        off += n
    return fields, offsets, off


def export_c_step(
    model: RobotModel,
    sensors: Sequence[str] | None,
    links: Sequence[str],
    kinds: Sequence[str],
    path: str | os.PathLike,
    *,
    dtype: torch.dtype = torch.float64,
    correction: Any = None,
    payload_links: Mapping[str, str] | None = None,
    joints: Sequence[str] | str | None = None,
    moving_base: bool = False,
    torque_rows: bool = False,
    covariance: bool = False,
    velocity_margin: float | None = None,
    ft_range: Mapping[str, float | Sequence[float]] | None = None,
    rank_rtol: float | None = None,
    gravity: Sequence[float] | None = None,
    prefix: str = "tc_estimator",
    march: str = "native",
    compiler: str | None = None,
    build: bool = True,
    ft_noise: Mapping[str, Sequence[float] | str] | Sequence[str] | None = None,
) -> dict[str, Any]:
    """Write the single-frame estimator as a C library: ``NAME.so``, ``.h``, ``.cpp``, ``.json``.

    Args:
        model: the robot.
        sensors: F/T sensor names (None: all).
        links: K slot links (or frames).
        kinds: K slot kinds (:data:`torchcontact.KINDS`).
        path: the library to write, ``NAME.so`` (the other files go beside it).
        dtype: ``torch.float64`` (default) or ``torch.float32`` computation and I/O.
        correction: a correction stack (:class:`torchcontact.residual.ResidualCorrection`, a
            checkpoint directory, or a list of them, one per sensor): its offset and inertial
            layers become the defaults of ``bias`` and ``theta``. A learned layer is not part
            of the library (run its ONNX graph beside it); it is recorded in the metadata.
        payload_links: sensor -> the link payloads attach to (default: the subtree's deepest
            body); its body's regressor is an output.
        joints: joint torques to output: None (all), names, or ``"sensed"`` (as the ONNX step
            graph; fewer outputs, less code).
        moving_base: inputs ``omega, domega, proper_acc`` (an IMU on the root body).
        torque_rows: inputs ``tau_measured, tau_mask``.
        covariance: input ``ft_cov``, output ``covariance``.
        velocity_margin: status bit 64 above this multiple of the URDF velocity limits.
        ft_range: sensor -> measuring range (status bit 64 beyond it).
        rank_rtol: rank tolerance of the solve (default: the dtype's).
        gravity: ``(3,)`` m/s^2 on a fixed base (default ``model.gravity``).
        prefix: prefix of the C symbols and macros (two libraries in one program need two).
        march: the compiler's ``-march`` (``native``: this CPU; e.g. ``x86-64-v3`` for others).
        compiler: the C++ compiler (default ``$CXX``, else ``g++``, ``c++`` or ``clang++``).
        build: compile the library (False: write the source, header and metadata only).
        ft_noise: every sensor's reading noise (as
            :func:`torchcontact.export.export_estimator`): the solve weighted by it, constants
            of the library (metadata ``ft_noise``); None: the unweighted ``pinv(A) b``.

    Returns:
        The metadata (also written to ``NAME.json`` and returned by ``<prefix>_metadata()``).

    Raises:
        InputError: an unknown sensor, link, kind or joint, a bad prefix, a correction stack for
            another robot or a sensor the estimator lacks.
        KernelBuildError: no compiler, or the build failed.

    Example:
        >>> import tempfile, torchcontact as tc
        >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> with tempfile.TemporaryDirectory() as d:
        ...     meta = export_c_step(m, None, ["hand_skin"], ["force"], f"{d}/arm.so", build=False)
        >>> meta["format"], meta["inputs"]["q"], meta["outputs"]["force"]
        ('torchcontact.cstep/1', [0, [7]], [0, [1, 3]])
    """
    from torchcontact import __version__
    from torchcontact.kernels import _cabi

    if dtype not in (torch.float32, torch.float64):
        raise InputError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    if not prefix.isidentifier() or not prefix.isascii():
        raise InputError(f"prefix must be a C identifier, got {prefix!r}")
    for k in kinds:
        if k not in KINDS:
            raise InputError(f"unknown kind {k!r}; expected one of {list(KINDS)}")
    m = model.to(dtype=dtype, device="cpu")
    if gravity is not None:
        m = m.with_gravity(gravity)
    est = ContactEstimator(
        m, sensors, rank_rtol=rank_rtol, velocity_margin=velocity_margin, ft_range=ft_range
    )
    names = list(est.sensor_names)
    em = est.layout(tuple(links), tuple(kinds))
    coords = em.torque_joints(joints if joints not in (None, "all") else None)
    stacks = _stacks(correction, model.to(dtype=torch.float64, device="cpu"), names)
    layouts = sensor_layouts(m, names, payload_links, *stack_defaults(stacks))
    corr = InertialCorrection(
        tuple(lay.bodies for lay in layouts), tuple(lay.payload_body for lay in layouts)
    )
    flags = (bool(moving_base), bool(torque_rows), bool(covariance))
    ftn = noise = None
    if ft_noise is not None:
        from torchcontact.noise import fixed_noise

        if torque_rows:
            raise InputError(
                "ft_noise with torque_rows: the torque rows' noise is not known (a weighted"
                " estimate needs every row's noise); export one or the other"
            )
        ftn = fixed_noise(ft_noise, names, list(m.ft_sensors))
        noise = tuple(ftn.sensors[s].std for s in names)
    prog = step_program(em, corr, coords, flags, noise)
    S, K = len(names), len(links)
    fin, in_off, in_size = _layout(prog.inputs, S, K, len(coords), names, names)
    fout, out_off, out_size = _layout(prog.outputs, S, K, len(coords), names, names)
    npd = np.dtype(str(dtype).removeprefix("torch."))
    defaults = np.zeros(in_size)
    for i, s in enumerate(names):
        o = fin["bias"][0] + 6 * i
        defaults[o : o + 6] = layouts[i].offset0
        o = fin[f"theta.{s}"][0]
        defaults[o : o + len(layouts[i].theta0)] = layouts[i].theta0
    meta: dict[str, Any] = {
        "format": C_FORMAT,
        "abi": C_ABI,
        "prefix": prefix,
        "robot": m.name,
        "urdf_sha256": m.urdf_sha256,
        # the robot's identity, as the ONNX graphs record it (one check decides for both)
        "robot_identity_sha256": m.identity.sha256,
        "robot_identity": m.identity.to_json(),
        "joint_names": list(m.joint_names),
        "sensors": [
            {"name": s.name, "joint": s.joint, "frame": s.frame, "direction": s.measure_direction}
            for s in est.sensors
        ],
        "slot_links": list(links),
        "slot_kinds": list(kinds),
        "slot_regions": [sl.region for sl in em.slots],
        "torque_joints": [m.joint_names[c] for c in coords],
        "dtype": str(npd),
        "moving_base": flags[0],
        "torque_rows": flags[1],
        "covariance": flags[2],
        "gravity": [float(g) for g in m.gravity],
        "rank_rtol": float(em.rank_rtol),
        "velocity_margin": velocity_margin,
        "in_size": in_size,
        "out_size": out_size,
        "inputs": {k: [o, list(sh)] for k, (o, sh, _) in fin.items()},
        "outputs": {k: [o, list(sh)] for k, (o, sh, _) in fout.items()},
        "units": {k: u for k, (_, _, u) in {**fin, **fout}.items()},
        "online": [lay.to_json(m.body_names) for lay in layouts],
        "correction": {
            s: {
                "source": c.source,
                "layers": c.layers,
                "in_library": [k for k in c.layers if k in ("offset", "inertial")],
                "weights_sha256": c.meta.get("weights_sha256"),
            }
            for s, c in stacks.items()
        },
        **({} if ftn is None else {"ft_noise": ftn.summary()}),
        "program_key": prog.key,
        "march": march,
        "torchcontact_version": __version__,
    }
    path = Path(path)
    text = json.dumps(meta, sort_keys=True)
    kernel, api, header = _cabi.emit_library(
        prog, "double" if npd == np.float64 else "float", prefix, in_off, out_off, in_size,
        out_size, fout["status"][0], text, defaults, {**_doc(fin, "IN"), **_doc(fout, "OUT")},
    )  # fmt: skip
    src = f"{kernel}\n{api}"
    for p, content in ((path.with_suffix(".cpp"), src), (path.with_suffix(".h"), header),
                       (path.with_suffix(".json"), json.dumps(meta, indent=1) + "\n")):  # fmt: skip
        _write_atomic(p, content)
    if build:
        meta["compiler"] = _cabi.build_library(kernel, api, path, march, compiler)
    return meta


def _doc(fields: Mapping[str, tuple[int, tuple[int, ...], str]], side: str) -> dict[str, tuple]:
    return {f"{side}_{k}": (o, sh, u) for k, (o, sh, u) in fields.items()}


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _stacks(correction: Any, model: RobotModel, sensors: Sequence[str]) -> dict[str, Any]:
    """Correction stacks by sensor (loaded from checkpoint directories when given as paths)."""
    from torchcontact.errors import CheckpointError
    from torchcontact.residual import ResidualCorrection

    if correction is None:
        return {}
    items = correction if isinstance(correction, (list, tuple)) else [correction]
    out: dict[str, Any] = {}
    for c in items:
        if isinstance(c, (str, os.PathLike)):
            try:
                c = ResidualCorrection.load(c, model)
            except CheckpointError as e:
                raise InputError(f"--residual: {e}") from None
        if not isinstance(c, ResidualCorrection):
            raise InputError(f"correction must be a ResidualCorrection or a checkpoint, got {c!r}")
        if c.model.urdf_sha256 != model.urdf_sha256:
            raise InputError(f"the correction of {c.sensor!r} was made for another robot")
        if c.sensor not in sensors:
            raise InputError(f"the correction is for sensor {c.sensor!r}, not one of {sensors}")
        if c.sensor in out:
            raise InputError(f"two corrections for sensor {c.sensor!r}")
        out[c.sensor] = c
    return out


def stack_defaults(
    stacks: Mapping[str, Any],
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The inertial change and the offset of correction stacks by sensor, float64 numpy.

    What the ``theta.<sensor>`` and ``bias`` inputs of an exported step default to (the C step,
    an ONNX step graph exported with ``online``).
    """
    theta0 = {s: c.graph.delta.detach().cpu().double().numpy() for s, c in stacks.items()
              if c.delta is not None}  # fmt: skip
    offsets = {s: c.offset.detach().cpu().double().numpy() for s, c in stacks.items()
               if c.offset is not None}  # fmt: skip
    return theta0, offsets
