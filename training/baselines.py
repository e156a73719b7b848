"""Classical corrections: contact-free prediction, constant offset, inertial re-identification.

The contact-free reading of a sensor is linear in the inertial parameters of the bodies beyond it
(the Newton-Euler body wrench ``I a + v x* I v`` is linear in the spatial inertia), when each body
is parametrised by ``theta_b = (m, m c, I_origin)`` -- mass, first moments and the rotational
inertia about the body origin (10 numbers). ``predict_ft = Y(q, qd, qdd) theta``; with a sensor
offset ``o`` the reading is ``Y theta + o``. :func:`inertial_regressor` builds ``Y`` column by
column from ``predict_ft`` on model copies with one parameter perturbed by one unit (exact, by
linearity); :class:`InertialLeastSquares` re-identifies ``theta`` and ``o`` from contact-free
frames.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

import torchcontact as tc

#: names of the 10 inertial parameters of one body, about its origin, body axes
PARAM_NAMES = ("m", "mcx", "mcy", "mcz", "Ixx", "Ixy", "Ixz", "Iyy", "Iyz", "Izz")
_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def no_contacts(n: int, dtype=torch.float64) -> tc.Contacts:
    """Zero contact slots for ``n`` frames (the contact-free prediction)."""
    return tc.Contacts((), (), torch.zeros(n, 0, 3, dtype=dtype))


def predict_free(est: tc.ContactEstimator, q, qd, qdd, sensor: str, chunk: int = 32768):
    """Contact-free reading ``(N, 6)`` numpy float64 predicted by ``est``'s model."""
    out = []
    for s in range(0, len(q), chunk):
        t = [
            torch.as_tensor(np.asarray(x[s : s + chunk]), dtype=torch.float64) for x in (q, qd, qdd)
        ]
        out.append(est.predict_ft(*t, no_contacts(len(t[0])))[sensor].numpy())
    return np.concatenate(out) if out else np.zeros((0, 6))


def subtree_bodies(model: tc.RobotModel, sensor: str) -> list[int]:
    """Bodies whose inertia the sensor measures (its child body's subtree)."""
    return sorted(model.subtree(model.ft_sensors[sensor].child_body))


def inertial_params(model: tc.RobotModel, bodies: list[int]) -> np.ndarray:
    """``(len(bodies) * 10,)`` parameters ``(m, m c, I_origin)`` per body (float64)."""
    out = []
    for b in bodies:
        m = float(model.mass[b])
        c = model.com[b].double().numpy()
        ic = model.inertia_com[b].double().numpy()
        io = ic + m * (c @ c * np.eye(3) - np.outer(c, c))
        out.append([m, *(m * c), *(io[i, j] for i, j in _SYM)])
    return np.asarray(out, float).reshape(-1)


def with_inertial_params(model: tc.RobotModel, bodies: list[int], theta: np.ndarray):
    """Copy of ``model`` whose ``bodies`` carry parameters ``theta`` (converted to com form).

    Masses must be nonzero (the com is ``h / m``); the copy need not be physically consistent.
    """
    theta = np.asarray(theta, float).reshape(len(bodies), 10)
    mass, com, inertia = model.mass.clone(), model.com.clone(), model.inertia_com.clone()
    for b, th in zip(bodies, theta, strict=True):
        m, h = th[0], th[1:4]
        io = np.zeros((3, 3))
        for v, (i, j) in zip(th[4:], _SYM, strict=True):
            io[i, j] = io[j, i] = v
        c = h / m
        ic = io - (h @ h * np.eye(3) - np.outer(h, h)) / m
        mass[b] = m
        com[b] = torch.as_tensor(c, dtype=model.dtype)
        inertia[b] = torch.as_tensor(ic, dtype=model.dtype)
    return replace(model, mass=mass, com=com, inertia_com=inertia)


def inertial_regressor(
    model: tc.RobotModel, sensor: str, q, qd, qdd, chunk: int = 8192
) -> np.ndarray:
    """Regressor ``Y (N, 6, P)`` with ``predict_ft(model) = Y @ inertial_params(model)``.

    Built from the public forward pass: the kinematics once, then the body wrenches
    ``I a + v x* I v`` of model copies with parameter ``j`` of every subtree body raised by one
    unit; each body's change, moved to the sensor frame, is its column ``j`` (exact, since body
    wrenches are linear in ``theta``). The reading is the wrench the parent side exerts on the
    sensor's subtree: the sum of the subtree's body wrenches, in the sensor frame about its origin,
    with the sign of ``measure_direction``. ``P = 10 * len(subtree_bodies(model, sensor))``.
    """
    bodies = subtree_bodies(model, sensor)
    theta0 = inertial_params(model, bodies).reshape(len(bodies), 10)
    s = model.ft_sensors[sensor]
    sign = 1.0 if s.measure_direction == "parent_to_child" else -1.0
    R_cs = torch.as_tensor(s.R_child_sensor, dtype=model.dtype)
    p_cs = torch.as_tensor(s.p_child_sensor, dtype=model.dtype)
    perturbed = []
    for j in range(10):
        th = theta0.copy()
        th[:, j] += 1.0
        perturbed.append(with_inertial_params(model, bodies, th))
    out = []
    for s0 in range(0, len(q), chunk):
        t = [
            torch.as_tensor(np.asarray(x[s0 : s0 + chunk]), dtype=model.dtype) for x in (q, qd, qdd)
        ]
        fp = tc.forward_pass(model, *t)
        # pose of the sensor frame in the root: T_root_child T_child_sensor
        R = fp.R[:, s.child_body] @ R_cs
        p = fp.p[:, s.child_body] + fp.R[:, s.child_body] @ p_cs
        f0 = tc.body_wrenches(model, fp)[:, bodies]
        cols = []
        for mj in perturbed:
            df = tc.body_wrenches(mj, fp)[:, bodies] - f0  # (n, nbs, 6) root frame, root origin
            force, moment = df[..., :3], df[..., 3:]
            moment = moment - torch.cross(p[:, None].expand_as(force), force, dim=-1)
            Rt = R.transpose(-1, -2)[:, None]
            cols.append(sign * torch.cat(((Rt @ force[..., None]), (Rt @ moment[..., None])), -2))
        # cols[j]: (n, nbs, 6, 1) -> Y[:, :, b * 10 + j]
        Y = torch.cat(cols, -1).permute(0, 2, 1, 3).reshape(len(t[0]), 6, -1)
        out.append(Y.numpy())
    return np.concatenate(out) if out else np.zeros((0, 6, 10 * len(bodies)))


@dataclass
class InertialLeastSquares:
    """Baseline (c): sensor offset plus re-identified inertial parameters, by least squares.

    Fits ``r = Y delta + o`` on contact-free frames, where ``r`` is the residual of the nominal
    model and ``delta`` the change of the subtree's inertial parameters. Columns are scaled to
    unit RMS and solved with ``lstsq(rcond)``: directions the trajectory does not excite (below
    ``rcond`` of the largest singular value) are left at the nominal values (minimum-norm
    ``delta``), so unidentifiable combinations are not invented.

    Attributes:
        rcond: relative singular-value cut-off.
        offset: ``(6,)`` fitted offset.
        delta: ``(P,)`` fitted parameter change.
        rank: numerical rank of the scaled design matrix.
    """

    rcond: float = 1e-6
    offset: np.ndarray | None = None
    delta: np.ndarray | None = None
    rank: int = 0
    model: tc.RobotModel | None = None
    sensor: str = ""

    def fit(
        self, model: tc.RobotModel, sensor: str, Y: np.ndarray, residual
    ) -> InertialLeastSquares:
        """Fit on contact-free frames.

        Args:
            model: the nominal robot.
            sensor: the sensor.
            Y: ``(n, 6, P)`` regressor of the frames (:func:`inertial_regressor`).
            residual: ``(n, 6)`` residuals of the nominal model.

        Returns:
            self, fitted.
        """
        n, _, P = Y.shape
        A = np.concatenate([np.broadcast_to(np.eye(6), (n, 6, 6)), Y], -1).reshape(n * 6, 6 + P)
        scale = np.sqrt((A**2).mean(0))
        scale[scale == 0] = 1.0
        x, _, rank, _ = np.linalg.lstsq(
            A / scale, np.asarray(residual).reshape(-1), rcond=self.rcond
        )
        x = x / scale
        self.offset, self.delta, self.rank = x[:6], x[6:], int(rank)
        self.model, self.sensor = model, sensor
        return self

    def correction(self, Y: np.ndarray) -> np.ndarray:
        """``(N, 6)`` predicted residual ``Y delta + o`` for regressors ``Y (N, 6, P)``."""
        return Y @ self.delta + self.offset

    def identified_model(self) -> tc.RobotModel:
        """The nominal model with the re-identified parameters (for inspection).

        It may be physically inconsistent in directions the data did not excite.
        """
        bodies = subtree_bodies(self.model, self.sensor)
        theta = inertial_params(self.model, bodies) + self.delta
        return with_inertial_params(self.model, bodies, theta)
