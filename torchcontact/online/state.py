"""What an online estimator keeps between frames: offsets, payloads, identification (numpy only).

One :class:`OnlineState` serves every backend (the torch estimator
:class:`~torchcontact.online.estimator.OnlineEstimator`, and the deployment runtime
:class:`torchcontact.runtime.EstimatorRuntime` on the C step and on an ONNX step graph exported
with ``online``). A backend's step
subtracts :meth:`OnlineState.bias` and the inertial change :meth:`OnlineState.theta` (the
correction stack's inertial layer plus the payload) from the readings, computes
``ft_model`` (the contact-free reading the model predicts with that inertial change) and the
regressor of each sensor's payload body, and hands them to :meth:`OnlineState.after_step`,
which updates the bias tracker on the contact-free sensors and feeds a running payload
identification.

Per sensor, the parameter vector ``theta`` lists ten inertial parameters
(:data:`~torchcontact.online.payload.PARAM_NAMES`, body frame, about the body origin) per body
of the sensor's subtree, in ascending body order (the layout of the correction stack's inertial
layer, :class:`torchcontact.residual.CorrectionGraph`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from torchcontact.errors import InputError
from torchcontact.online.bias import BiasState, BiasTracker
from torchcontact.online.payload import Payload, PayloadIdentifier

__all__ = ["OnlineState", "SensorLayout", "payload_body", "sensor_layouts"]


@dataclass(frozen=True)
class SensorLayout:
    """One sensor as the online state sees it.

    Attributes:
        name: the sensor.
        bodies: model body indices of its subtree, ascending (``theta``'s layout).
        frames: link (or joint frame) name -> ``(body, R_body_frame (3, 3), p_body_frame (3,))``
            for every frame on those bodies (where a payload can be attached).
        payload_link: the default link of :meth:`OnlineState.set_payload`, whose body's regressor
            the backend computes (identification).
        theta0: ``(10 len(bodies),)`` the correction stack's inertial change (zeros: none).
    """

    name: str
    bodies: tuple[int, ...]
    frames: Mapping[str, tuple[int, Any, Any]]
    payload_link: str
    theta0: np.ndarray = field(default_factory=lambda: np.zeros(0))
    offset0: np.ndarray = field(default_factory=lambda: np.zeros(6))

    @property
    def payload_body(self) -> int:
        """The body of :attr:`payload_link`."""
        return int(self.frames[self.payload_link][0])

    def to_json(self, body_names: Sequence[str]) -> dict[str, Any]:
        """The ``online`` metadata entry of exported steps (C libraries, ONNX step graphs).

        Args:
            body_names: the model's body names (listed beside the indices, for people).
        """
        return {
            "sensor": self.name,
            "bodies": [body_names[b] for b in self.bodies],
            "body_index": [int(b) for b in self.bodies],
            "payload_link": self.payload_link,
            "frames": {
                k: [
                    int(b),
                    np.asarray(R, float).reshape(-1).tolist(),
                    np.asarray(p, float).tolist(),
                ]
                for k, (b, R, p) in self.frames.items()
            },
            "offset": np.asarray(self.offset0, float).reshape(6).tolist(),
            "theta0": np.asarray(self.theta0, float).reshape(-1).tolist(),
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> SensorLayout:
        """Inverse of :meth:`to_json` (``offset``/``theta0`` default to zeros: round-1 libraries).

        Raises:
            InputError: a malformed entry.
        """
        try:
            bodies = tuple(int(b) for b in d["body_index"])
            frames = {
                k: (int(b), np.asarray(R, float).reshape(3, 3), np.asarray(p, float).reshape(3))
                for k, (b, R, p) in d["frames"].items()
            }
            theta0 = np.asarray(d.get("theta0", np.zeros(10 * len(bodies))), float)
            offset0 = np.asarray(d.get("offset", np.zeros(6)), float).reshape(6)
            return cls(str(d["sensor"]), bodies, frames, str(d["payload_link"]), theta0, offset0)
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"malformed online metadata entry: {e!r}") from None


class OnlineState:
    """Bias tracking, payloads and payload identification of one estimator's sensors.

    Args:
        sensors: per sensor its :class:`SensorLayout`, in the estimator's sensor order.
        slot_regions: per contact slot, the index of the sensor whose region it lies in.
        tracker: the bias tracker (its initial offsets are the correction stack's offsets).
        track: update the tracker on contact-free frames (False: the offsets change only by
            :meth:`tare` and :meth:`identify_payload`).
        tare_frames: frames kept for :meth:`tare` (it averages up to that many).
    """

    def __init__(
        self,
        sensors: Sequence[SensorLayout],
        slot_regions: Sequence[int],
        tracker: BiasTracker,
        *,
        track: bool = True,
        tare_frames: int = 100,
    ) -> None:
        self.sensors = tuple(sensors)
        names = tuple(s.name for s in self.sensors)
        if tracker.sensors != names:
            raise InputError(f"the bias tracker tracks {tracker.sensors}, the estimator {names}")
        self.slot_regions = np.asarray(slot_regions, dtype=np.int64)
        self._regions = self.slot_regions.tolist()
        self._all_free = np.ones(len(self.sensors), dtype=bool)
        self.tracker, self.track = tracker, bool(track)
        self.payloads: list[Payload | None] = [None] * len(self.sensors)
        self._theta = [np.asarray(s.theta0, float).copy() for s in self.sensors]
        for s, th in zip(self.sensors, self._theta, strict=True):
            if th.shape != (10 * len(s.bodies),):
                raise InputError(f"theta0 of {s.name}: expected {10 * len(s.bodies)} values")
        self.identifiers: list[PayloadIdentifier | None] = [None] * len(self.sensors)
        self._recent: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=max(1, tare_frames))
        self.last: BiasState = tracker.state

    @classmethod
    def build(
        cls,
        sensors: Sequence[SensorLayout],
        slot_regions: Sequence[int],
        track_bias: bool | BiasTracker = False,
        tracker_options: Mapping[str, Any] | None = None,
    ) -> OnlineState:
        """The online state of a backend, as every backend makes it.

        Args:
            sensors: per sensor its layout (the offsets start at its ``offset0``).
            slot_regions: per slot the index of its sensor.
            track_bias: True (a :class:`BiasTracker` with ``tracker_options``), a tracker, or
                False (offsets change only by :meth:`tare` and :meth:`identify_payload`).
            tracker_options: :class:`BiasTracker` keyword arguments (``time_constant``,
                ``period``, ``ft_std``, ``gate``, ...).

        Raises:
            InputError: bad tracker options.
        """
        tracker = track_bias if isinstance(track_bias, BiasTracker) else None
        if tracker is None:
            opts = dict(tracker_options or {})
            opts.setdefault("offset", np.stack([np.asarray(s.offset0, float) for s in sensors]))
            try:
                tracker = BiasTracker([s.name for s in sensors], **opts)
            except TypeError as e:  # an unknown option
                raise InputError(f"bias tracker options: {e}") from None
        return cls(sensors, slot_regions, tracker, track=bool(track_bias))

    # ----------------------------------------------------------------------------- per frame
    @property
    def names(self) -> tuple[str, ...]:
        """Sensor names."""
        return tuple(s.name for s in self.sensors)

    def index(self, sensor: str | None) -> int:
        """Index of ``sensor`` (None: the only sensor)."""
        if sensor is None:
            if len(self.sensors) != 1:
                raise InputError(f"name the sensor: one of {list(self.names)}")
            return 0
        if sensor not in self.names:
            raise InputError(f"unknown sensor {sensor!r}; the estimator has {list(self.names)}")
        return self.names.index(sensor)

    def bias(self) -> np.ndarray:
        """``(S, 6)`` offsets to subtract from the readings ``[N; N m]``."""
        return self.tracker.offset

    def theta(self, i: int) -> np.ndarray:
        """Sensor ``i``'s inertial change (stack layer + payload), ``(10 len(bodies),)``."""
        return self._theta[i]

    def contact_free(self, active: Any = None, contact_free: Any = None) -> np.ndarray:
        """``(S,)`` which sensors may update their offset this frame.

        A sensor is free when no active slot lies in its region and the caller's
        ``contact_free`` signal (bool, or ``(S,)`` per sensor, e.g. from a contact localizer or
        a user's switch; None: no signal) does not say otherwise.
        """
        free = [True] * len(self.sensors)  # a few sensors and slots: plain Python is fastest
        if active is not None and self._regions:
            on = (active if type(active) is np.ndarray else np.asarray(active, np.float64)).ravel()
            if on.size != len(self._regions):
                raise InputError(f"active must have {len(self._regions)} values")
            for k, a in enumerate(on.tolist()):
                if a > 0.5:
                    free[self._regions[k]] = False
        if contact_free is not None:
            user = np.asarray(contact_free, dtype=bool)
            user = np.broadcast_to(user, (len(free),)) if user.ndim == 0 else user.reshape(-1)
            free = [f and bool(u) for f, u in zip(free, user.tolist(), strict=True)]
        return np.array(free)

    def after_step(
        self,
        ft: np.ndarray,
        ft_model: np.ndarray,
        free: np.ndarray,
        regressors: Sequence[np.ndarray | None] | None = None,
        t: float | None = None,
    ) -> BiasState:
        """Update from one estimated frame.

        Args:
            ft: ``(S, 6)`` raw readings.
            ft_model: ``(S, 6)`` the model's contact-free prediction with :meth:`theta`.
            free: ``(S,)`` from :meth:`contact_free`.
            regressors: per sensor the ``(6, 10)`` regressor of its payload body (needed while
                identifying).
            t: the frame's time, s (None: one nominal period on).

        Returns:
            The bias state after the frame (also :attr:`last`).
        """
        z = np.asarray(ft, dtype=np.float64) - ft_model
        self._recent.append((z, free.copy()))
        use = free if self.track else np.zeros(len(self.sensors), dtype=bool)
        for i, ident in enumerate(self.identifiers):
            if ident is None:
                continue
            if use is free:
                use = free.copy()
            use[i] = False  # the identification fits the offset itself
            Y = None if regressors is None else regressors[i]
            if Y is None:
                raise InputError(f"identifying the payload of {self.names[i]} needs its regressor")
            ident.update(Y, z[i], bool(free[i]))  # no payload while identifying: z is all of it
        self.last = self.tracker.update(z, use, t)
        return self.last

    # ----------------------------------------------------------------------------- commands
    def tare(self, frames: int = 1) -> BiasState:
        """Re-zero now: each offset becomes the mean residual of the last ``frames`` frames.

        The residual is the reading less the model's prediction at the current pose, so the
        arm need not be in a zero pose.

        Raises:
            InputError: no frame yet, or a contact active in one of those frames.
        """
        if not self._recent:
            raise InputError("tare() needs a frame first: call step() once")
        recent = list(self._recent)[-max(1, int(frames)) :]
        z = np.stack([r[0] for r in recent])
        free = np.stack([r[1] for r in recent])
        self.last = self.tracker.tare(z, free, len(recent))
        return self.last

    def set_payload(self, payload: Payload | None, sensor: str | None = None) -> None:
        """Replace the payload carried by a sensor (a tool change; None: no payload).

        Args:
            payload: a :class:`Payload` (its ``link``, default the sensor's payload link, must
                be a link the sensor carries), or None.
            sensor: the sensor (None: the only one).

        Raises:
            InputError: an unknown sensor or link, a link the sensor does not carry.
        """
        i = self.index(sensor)
        s = self.sensors[i]
        th = np.asarray(s.theta0, float).copy()
        if payload is not None:
            if not isinstance(payload, Payload):
                raise InputError(f"expected a Payload, got {type(payload).__name__}")
            link = payload.link or s.payload_link
            if link not in s.frames:
                raise InputError(
                    f"payload link {link!r} is not carried by sensor {s.name!r} (links: "
                    f"{sorted(s.frames)[:12]}...)"
                )
            body, R, t = s.frames[link]
            j = s.bodies.index(int(body))
            th[10 * j : 10 * j + 10] += payload.params(R, t)
            payload = Payload(payload.mass, payload.com, payload.inertia, link)
        self.payloads[i] = payload
        self._theta[i] = th

    def start_identification(self, sensor: str | None = None, **kwargs: Any) -> None:
        """Start identifying a sensor's payload from the next contact-free frames (a tool change).

        The sensor's payload is cleared (the fit is the whole payload) and its offset is not
        tracked meanwhile (the fit includes it); :meth:`identify_payload` sets both.

        Args:
            sensor: the sensor (None: the only one).
            kwargs: :class:`PayloadIdentifier` options (``params``, ``mass_tol``, ...); the
                noise covariance defaults to the bias tracker's.
        """
        i = self.index(sensor)
        kwargs.setdefault("ft_cov", self.tracker.R[i])
        self.identifiers[i] = PayloadIdentifier(**kwargs)
        self.set_payload(None, self.names[i])

    def identify_payload(self, sensor: str | None = None, apply: bool = True) -> Payload:
        """The payload identified so far; with ``apply`` it replaces the current one.

        Also re-zeroes the sensor's offset to the one fitted with it and ends the identification
        (with ``apply``).

        Raises:
            InputError: no identification running for this sensor.
            NotIdentifiableError: the data cannot identify it yet (keep moving, then ask again).
        """
        i = self.index(sensor)
        ident = self.identifiers[i]
        if ident is None:
            raise InputError(
                f"no payload identification is running for {self.names[i]}: call"
                " start_identification() first, then move the robot without contact"
            )
        s = self.sensors[i]
        _, R, t = s.frames[s.payload_link]
        payload = ident.identify(R, t, s.payload_link)
        if apply:
            est = ident.estimate()
            self.set_payload(payload, s.name)
            self.tracker.offset[i] = est.offset
            self.tracker.p[i] = 1.0 / max(est.frames, 1)
            self.tracker.since[i] = 0.0
            self.identifiers[i] = None
        return payload


def payload_body(model: Any, sensor: str) -> int:
    """The default payload body of a sensor: the deepest body of its subtree (the end effector).

    The same rule as the simulator's payload (:func:`torchcontact.simulation.effect_links`).
    """
    sub_ = model.subtree(model.ft_sensors[sensor].child_body)
    depth = {b: d for d, (s, e) in enumerate(model.levels) for b in range(s, e)}
    return max(sub_, key=lambda b: (depth[b], b))


def sensor_layouts(
    model: Any,
    sensors: Sequence[str],
    payload_links: Mapping[str, str] | None = None,
    theta0: Mapping[str, Any] | None = None,
    offsets: Mapping[str, Any] | None = None,
) -> list[SensorLayout]:
    """Per sensor its :class:`SensorLayout` (numpy; ``model`` is read, not computed with).

    Args:
        model: the robot (a :class:`~torchcontact.RobotModel`).
        sensors: the sensors, in the estimator's order.
        payload_links: sensor -> the link payloads attach to (default: the deepest body of the
            sensor's subtree, by its link name).
        theta0: sensor -> ``(10 B,)`` the correction stack's inertial change over the subtree.
        offsets: sensor -> ``(6,)`` the correction stack's offset.

    Raises:
        InputError: an unknown link, or one the sensor does not carry.
    """
    out = []
    for s in sensors:
        bodies = tuple(model.subtree(model.ft_sensors[s].child_body))
        frames = {
            name: (fr.body, np.asarray(fr.R_body_frame, float), np.asarray(fr.p_body_frame, float))
            for name, fr in model.frames.items()
            if fr.body in bodies
        }
        link = (payload_links or {}).get(s) or model.body_names[payload_body(model, s)]
        if link not in frames:
            raise InputError(
                f"payload link {link!r} is not carried by sensor {s!r} of {model.name}"
            )
        th = np.zeros(10 * len(bodies))
        if theta0 is not None and theta0.get(s) is not None:
            th = np.asarray(theta0[s], dtype=np.float64).reshape(-1)
            if th.shape != (10 * len(bodies),):
                raise InputError(f"theta0[{s!r}] must have {10 * len(bodies)} values")
        off = np.zeros(6)
        if offsets is not None and offsets.get(s) is not None:
            off = np.asarray(offsets[s], dtype=np.float64).reshape(6)
        out.append(SensorLayout(s, bodies, frames, link, th, off))
    return out
