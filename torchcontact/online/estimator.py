"""The torch estimator on the robot: bias tracked from the model, payloads, identification.

:class:`OnlineEstimator` runs :class:`~torchcontact.ContactEstimator` frame by frame with the
online state of :mod:`torchcontact.online.state` (the same class the C step's runtime uses), so
one frame is::

    ft_model = predict_ft(q, qd, qdd) + Y theta (+ a learned layer)   # the contact-free reading
    estimate(ft - bias - (ft_model - predict_ft), contacts)            # the contact wrenches
    bias <- tracker(ft - ft_model) on contact-free sensors

with ``theta`` the correction stack's inertial change plus the payload, ``bias`` the stack's
offset then the tracked one. It is also the torch reference the C step is tested against.
:func:`track_log` does the same over a whole log offline, with the smoother
(:func:`torchcontact.online.bias.smooth_bias`): the building block of ``estimate --track-bias``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchcontact.contacts import Contacts
from torchcontact.errors import InputError
from torchcontact.estimation import ContactEstimator
from torchcontact.model import RobotModel
from torchcontact.online.bias import BiasState, BiasTrack, BiasTracker, smooth_bias
from torchcontact.online.cstep import _stacks, sensor_layouts, stack_defaults
from torchcontact.online.payload import Payload
from torchcontact.online.state import OnlineState
from torchcontact.residual import ResidualCorrection, sensor_regressor

__all__ = ["LogTrack", "OnlineEstimator", "track_log"]


class OnlineEstimator:
    """Contact estimation frame by frame with bias tracking and payloads (torch).

    Args:
        model: the robot (float64 recommended; its dtype is the computation's).
        sensors: F/T sensors (None: all).
        links: K slot links.
        kinds: K slot kinds.
        correction: correction stacks (a :class:`~torchcontact.residual.ResidualCorrection`, a
            checkpoint directory, or one per sensor): offset -> the initial bias, inertial layer
            -> ``theta``, learned layer -> part of ``ft_model``.
        payload_links: sensor -> the link payloads attach to (default: the subtree's deepest body).
        track_bias: track the offsets on contact-free frames (True, a
            :class:`~torchcontact.online.bias.BiasTracker`, or False).
        tracker_options: :class:`BiasTracker` keyword arguments.
        backend: the estimator's backend (``"eager"``, ``"cpu"``, ...).

    Example:
        >>> import torch, torchcontact as tc
        >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> on = OnlineEstimator(m, None, ["hand_skin"], ["force"], track_bias=True,
        ...                      backend="eager")
        >>> q = torch.zeros(7, dtype=torch.float64)
        >>> out = on.step(q, q, q, torch.zeros(6), active=[1.0])  # in contact: no update
        >>> ft = out["ft_model"][0] + 2.0  # the model's reading plus a 2 N offset
        >>> for _ in range(3):  # contact-free frames
        ...     out = on.step(q, q, q, ft, active=[0.0])
        >>> [round(v, 3) for v in out["bias"].offset[0, :3].tolist()], out["bias"].updated
        ([2.0, 2.0, 2.0], array([ True]))
    """

    def __init__(
        self,
        model: RobotModel,
        sensors: Sequence[str] | None = None,
        links: Sequence[str] = (),
        kinds: Sequence[str] = (),
        *,
        correction: Any = None,
        payload_links: Mapping[str, str] | None = None,
        track_bias: bool | BiasTracker = False,
        tracker_options: Mapping[str, Any] | None = None,
        backend: str = "auto",
    ) -> None:
        self.model = model
        self.estimator = ContactEstimator(model, sensors, backend=backend)
        names = list(self.estimator.sensor_names)
        self.sensor_names = tuple(names)
        self.links, self.kinds = tuple(links), tuple(kinds)
        em = self.estimator.layout(self.links, self.kinds)
        stacks = _stacks(correction, model, names)
        self.layouts = sensor_layouts(model, names, payload_links, *stack_defaults(stacks))
        # the learned layers, alone (their offset and inertial layers are bias and theta)
        self._learned = {
            s: ResidualCorrection(model, s, learned=c.learned, features=c.features)
            for s, c in stacks.items()
            if c.learned is not None
        }
        self.state = OnlineState.build(
            self.layouts, [s.region for s in em.slots], track_bias, tracker_options
        )
        self._none = Contacts((), (), torch.zeros(1, 0, 3, dtype=model.dtype))

    def _frame(self, x: Any, name: str) -> Tensor:
        t = torch.as_tensor(np.asarray(x, dtype=np.float64)).to(self.model.dtype).reshape(1, -1)
        if t.shape[1] != self.model.nv:
            raise InputError(f"{name} must have {self.model.nv} values, got {t.shape[1]}")
        return t

    def model_terms(
        self, q: Tensor, qd: Tensor, qdd: Tensor, extra: Mapping[str, Any] | None = None
    ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """What the model explains for ``N`` frames.

        Args:
            q: ``(N, nv)`` in ``model.joint_names`` order; ``qd``, ``qdd`` likewise.
            qd: ``(N, nv)``.
            qdd: ``(N, nv)``.
            extra: the learned layers' extra columns, name -> ``(N,)``.

        Returns:
            ``ft_model (N, S, 6)`` (the contact-free reading: nominal + ``Y theta`` + learned),
            ``explained (N, S, 6)`` (``Y theta`` + learned: subtracted from the readings besides
            the bias), per sensor ``(N, 6, 10)`` regressor of its payload body.
        """
        n = q.shape[0]
        nominal = self.estimator.predict_ft(q, qd, qdd, Contacts(
            (), (), q.new_zeros(n, 0, 3)))  # fmt: skip
        ft_model = np.zeros((n, len(self.layouts), 6))
        explained = np.zeros_like(ft_model)
        regs = []
        for i, lay in enumerate(self.layouts):
            Y = sensor_regressor(self.model, lay.name, q, qd, qdd, lay.bodies)
            th = torch.as_tensor(self.state.theta(i)).to(Y)
            part = (Y @ th).double()
            if lay.name in self._learned:
                part = part + self._learned[lay.name].correction(q, qd, qdd, extra).double()
            explained[:, i] = part.cpu().numpy()
            ft_model[:, i] = nominal[lay.name].double().cpu().numpy() + explained[:, i]
            j = lay.bodies.index(lay.payload_body)
            regs.append(Y[..., 10 * j : 10 * j + 10].double().cpu().numpy())
        return ft_model, explained, regs

    def step(
        self,
        q: Any,
        qd: Any,
        qdd: Any,
        ft: Any,
        positions: Any = None,
        active: Any = None,
        directions: Any = None,
        wrenches: Any = None,
        *,
        extra: Mapping[str, float] | None = None,
        contact_free: Any = None,
        t: float | None = None,
    ) -> dict[str, Any]:
        """Estimate one frame from the raw readings, then update the online state.

        Arguments and returns as :meth:`torchcontact.runtime.EstimatorRuntime.step` of an
        online step (``active`` defaults to all slots active), plus ``extra`` (the learned
        layers' extra columns, name -> value).
        """
        K, S = len(self.links), len(self.sensor_names)
        qt, qdt, qddt = (self._frame(x, n) for x, n in ((q, "q"), (qd, "qd"), (qdd, "qdd")))
        ftv = np.asarray(ft, dtype=np.float64).reshape(S, 6)
        ex = None if extra is None else {k: np.atleast_1d(v) for k, v in extra.items()}
        ft_model, explained, regs = self.model_terms(qt, qdt, qddt, ex)
        corrected = ftv - self.state.bias() - explained[0]
        dt = self.model.dtype

        def opt(x: Any, shape: tuple[int, ...], fill: float = 0.0) -> Tensor:
            if x is None:
                return torch.full((1, *shape), fill, dtype=dt)
            return torch.as_tensor(np.asarray(x, np.float64)).to(dt).reshape(1, *shape)

        act = opt(active, (K,), 1.0)
        c = Contacts(
            self.links, self.kinds, opt(positions, (K, 3)),
            directions=opt(directions, (K, 3)) if "force_dir" in self.kinds else None,
            wrenches=opt(wrenches, (K, 6)) if "known" in self.kinds else None,
            active=act > 0.5,
        )  # fmt: skip
        r = self.estimator.estimate(
            qt, qdt, qddt, {s: torch.as_tensor(corrected[i]).to(dt)[None]
                            for i, s in enumerate(self.sensor_names)}, c,
        )  # fmt: skip
        status = int(r.status[0])
        free = self.state.contact_free(act[0].numpy(), contact_free) & (status == 0)
        bias = self.state.after_step(ftv, ft_model[0], free, [y[0] for y in regs], t)
        return {
            "force": r.force[0].double().numpy(),
            "moment": r.moment[0].double().numpy(),
            "joint_torques": r.joint_torques[0].double().numpy(),
            "rank": np.array([int(r.rank[s][0]) for s in self.sensor_names]),
            "unknowns": np.array([int(r.unknowns[s][0]) for s in self.sensor_names]),
            "residual": np.array([float(r.residual[s][0]) for s in self.sensor_names]),
            "status": status,
            "ft_model": ft_model[0],
            "bias": bias,
        }

    # ------------------------------------------------------------------------------ commands
    def tare(self, frames: int = 1) -> BiasState:
        """Re-zero the offsets now, from the model (refused during a contact)."""
        return self.state.tare(frames)

    def set_payload(
        self,
        mass: float | Payload | None,
        com: Any = (0.0, 0.0, 0.0),
        inertia: Any = None,
        *,
        link: str | None = None,
        sensor: str | None = None,
    ) -> Payload | None:
        """A tool change (see :meth:`torchcontact.runtime.EstimatorRuntime.set_payload`)."""
        if mass is None or isinstance(mass, Payload):
            payload = mass
        else:
            payload = Payload(mass, com, np.zeros((3, 3)) if inertia is None else inertia, link)
        self.state.set_payload(payload, sensor)
        return self.state.payloads[self.state.index(sensor)]

    def start_identification(self, sensor: str | None = None, **kwargs: Any) -> None:
        """Identify the payload from the next contact-free frames."""
        self.state.start_identification(sensor, **kwargs)

    def identify_payload(self, sensor: str | None = None, apply: bool = True) -> Payload:
        """The identified payload (refused until the data identify it), applied by default."""
        return self.state.identify_payload(sensor, apply)


class LogTrack(NamedTuple):
    """The readings of a log corrected with the tracked bias (:func:`track_log`).

    Attributes:
        ft: ``(N, S, 6)`` corrected readings: raw less the bias, ``Y theta`` and learned layers.
        bias: the :class:`~torchcontact.online.bias.BiasTrack` (offsets per frame).
        ft_model: ``(N, S, 6)`` the contact-free model reading.
    """

    ft: np.ndarray
    bias: BiasTrack
    ft_model: np.ndarray


def track_log(
    online: OnlineEstimator,
    q: Any,
    qd: Any,
    qdd: Any,
    ft: Any,
    contact_free: Any,
    t: Any = None,
    *,
    extra: Mapping[str, Any] | None = None,
    smoother: bool = True,
    chunk: int = 16384,
    **options: Any,
) -> LogTrack:
    """Track the offsets over a whole log and correct its readings (offline; ``--track-bias``).

    Args:
        online: the estimator (its correction stacks and payloads give ``ft_model``).
        q: ``(N, nv)`` joint positions in model order; ``qd``, ``qdd`` likewise.
        qd: ``(N, nv)``.
        qdd: ``(N, nv)``.
        ft: ``(N, S, 6)`` or ``(N, 6)`` raw readings.
        contact_free: ``(N,)`` or ``(N, S)``: frames with no contact on the sensor.
        t: ``(N,)`` time stamps, s.
        extra: the learned layers' extra columns, name -> ``(N,)``.
        smoother: forward-backward (RTS) smoothing; False: the causal filter only.
        chunk: frames per batched model evaluation.
        options: :func:`smooth_bias` options (``time_constant``, ``ft_std``, ...); the prior
            offset defaults to the estimator's current bias.

    Returns:
        :class:`LogTrack`.
    """
    dt = online.model.dtype
    qs = [torch.as_tensor(np.asarray(x, np.float64)).to(dt) for x in (q, qd, qdd)]
    n, S = qs[0].shape[0], len(online.sensor_names)
    raw = np.asarray(ft, dtype=np.float64).reshape(n, S, 6)
    ft_model = np.empty((n, S, 6))
    explained = np.empty((n, S, 6))
    for s in range(0, n, chunk):
        sl = slice(s, min(n, s + chunk))
        ex = None if extra is None else {k: np.asarray(v)[sl] for k, v in extra.items()}
        ft_model[sl], explained[sl], _ = online.model_terms(*(x[sl] for x in qs), ex)
    options.setdefault("offset", online.state.bias())
    if "ft_std" not in options:
        options.setdefault("ft_cov", online.state.tracker.R)
    track = smooth_bias(raw - ft_model, contact_free, t, smoother=smoother, **options)
    return LogTrack(raw - track.offset - explained, track, ft_model)
