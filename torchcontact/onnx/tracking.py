"""Bias tracking and payloads on a packed step, the same for every backend (numpy only).

A step with online inputs and outputs (a C step library; an ONNX step graph exported with
``online``, :mod:`torchcontact.onnx.step.online`) takes each sensor's offset ``bias (S, 6)`` and
inertial change ``theta.<sensor>`` and returns the model's contact-free reading
``ft_model (S, 6)`` and the payload regressors ``regressor.<sensor> (6, 10)``.
:class:`StepOnline` connects such a step to the one
:class:`~torchcontact.online.state.OnlineState`: before each call it writes the tracked offsets
into the packed input, after it hands the model's reading to the tracker (and to a running
payload identification), and its commands (``tare``, ``set_payload``, ``start_identification``,
``identify_payload``) write the inertial change into the packed input.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from torchcontact.online.bias import BiasState, BiasTracker
from torchcontact.online.payload import Payload
from torchcontact.online.state import OnlineState, SensorLayout

__all__ = ["StepOnline"]


class StepOnline:
    """The online state of one packed step.

    Args:
        metadata: the step's metadata (``online``: per sensor its
            :meth:`~torchcontact.online.state.SensorLayout.to_json`; ``slot_regions``).
        inputs: views of the packed input by field (``bias``, ``theta.<sensor>``, ``active``).
        outputs: the packed output's layout ``field -> (offset, shape)``.
        write_defaults: write the layouts' offsets and inertial changes into the packed input
            (an ONNX step); False: take them from it (a C library's own defaults).
        track_bias: True (a :class:`~torchcontact.online.bias.BiasTracker` with
            ``tracker_options``), a tracker, or False (the offsets change only by :meth:`tare`
            and :meth:`identify_payload`).
        tracker_options: :class:`BiasTracker` keyword arguments.

    Attributes:
        state: the :class:`~torchcontact.online.state.OnlineState`.
    """

    def __init__(
        self,
        metadata: Mapping[str, Any],
        inputs: Mapping[str, np.ndarray],
        outputs: Mapping[str, tuple[int, tuple[int, ...]]],
        *,
        write_defaults: bool,
        track_bias: bool | BiasTracker = False,
        tracker_options: Mapping[str, Any] | None = None,
    ) -> None:
        layouts = [SensorLayout.from_json(d) for d in metadata["online"]]
        self._bias = inputs["bias"]
        self._theta = [inputs[f"theta.{lay.name}"] for lay in layouts]
        self._active = inputs.get("active")
        if write_defaults:
            for i, lay in enumerate(layouts):
                self._bias[i] = lay.offset0
                self._theta[i][...] = lay.theta0
        layouts = [
            dataclasses.replace(
                lay,
                offset0=self._bias[i].astype(np.float64),
                theta0=self._theta[i].astype(np.float64),
            )  # fmt: skip
            for i, lay in enumerate(layouts)
        ]
        self.state = OnlineState.build(
            layouts, metadata["slot_regions"], track_bias, tracker_options
        )
        S = len(layouts)
        o, _ = outputs["ft_model"]
        self._ft_model = (o, o + 6 * S, (S, 6))
        self._regs = [outputs[f"regressor.{lay.name}"][0] for lay in layouts]

    @property
    def names(self) -> tuple[str, ...]:
        """The sensors."""
        return self.state.names

    def before(self) -> None:
        """Write the tracked offsets into the packed input (before each call)."""
        self._bias[...] = self.state.tracker.offset

    def after(
        self,
        out: np.ndarray,
        ft: np.ndarray,
        status: int,
        contact_free: Any = None,
        t: float | None = None,
    ) -> tuple[np.ndarray, BiasState]:
        """Update the online state from one estimated frame.

        Args:
            out: the packed output.
            ft: ``(S, 6)`` the readings the step was given (before the offset).
            status: the frame's status (a frame with one never updates the offsets).
            contact_free: the caller's contact-free signal (bool or ``(S,)``; see
                :meth:`OnlineState.contact_free`).
            t: the frame's time, s (None: one nominal period on).

        Returns:
            ``(ft_model (S, 6) float64, BiasState)``.
        """
        st = self.state
        a, b, sh = self._ft_model
        ft_model = out[a:b].reshape(sh)
        if ft_model.dtype != np.float64:
            ft_model = ft_model.astype(np.float64)
        free = st.contact_free(self._active, contact_free)
        if status:
            free[:] = False
        regs = None
        if st.identifiers.count(None) != len(st.identifiers):  # only an identification needs them
            regs = [out[o : o + 60].reshape(6, 10).astype(np.float64) for o in self._regs]
        return ft_model, st.after_step(ft, ft_model, free, regs, t)

    # ------------------------------------------------------------------------------ commands
    def _sync(self, sensor: str | None) -> int:
        i = self.state.index(sensor)
        self._theta[i][...] = self.state.theta(i)
        return i

    def tare(self, frames: int = 1) -> BiasState:
        """Re-zero the offsets now, from the model (:meth:`OnlineState.tare`)."""
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
        """The payload a sensor carries from the next frame on (:meth:`OnlineState.set_payload`).

        Args:
            mass: kg, or a :class:`~torchcontact.online.payload.Payload`, or None (none).
            com: ``(3,)`` centre of mass in ``link``'s frame, m.
            inertia: ``(3, 3)`` about the centre of mass, link axes, kg m^2 (default: a point).
            link: the link it is attached to (default: the sensor's payload link).
            sensor: the sensor (None: the only one).

        Raises:
            InputError: a non-physical payload, a link the sensor does not carry.
        """
        if mass is None or isinstance(mass, Payload):
            payload = mass
        else:
            payload = Payload(mass, com, np.zeros((3, 3)) if inertia is None else inertia, link)
        self.state.set_payload(payload, sensor)
        return self.state.payloads[self._sync(sensor)]

    def start_identification(self, sensor: str | None = None, **kwargs: Any) -> None:
        """Identify the payload from the next contact-free frames (a tool change)."""
        self.state.start_identification(sensor, **kwargs)
        self._sync(sensor)

    def identify_payload(self, sensor: str | None = None, apply: bool = True) -> Payload:
        """The identified payload (refused until the data identify it), applied by default."""
        p = self.state.identify_payload(sensor, apply)
        self._sync(sensor)
        return p

    def identifying(self) -> list[str]:
        """The sensors whose payload is being identified."""
        return [s for s, i in zip(self.names, self.state.identifiers, strict=True) if i is not None]
