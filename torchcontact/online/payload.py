"""Payloads at run time: physical inertial parameters and their identification (numpy only).

A payload (a tool, a grasped object) is a rigid body attached to a link the F/T sensor carries.
Its effect on the reading is linear in its ten inertial parameters about the body origin
``theta = (m, m c, I_origin)`` (:data:`PARAM_NAMES`, the regressor form of Newton-Euler: Atkeson,
An and Hollerbach 1986), through the sensor regressor ``Y`` of that body
(:func:`torchcontact.residual.sensor_regressor`, or the C step's ``regressor`` output)::

    ft = ft_model + Y theta + offset + noise

- :class:`Payload` is what ``set_payload(mass, com, inertia)`` takes: it refuses a non-physical
  body (a mass that is not positive, an inertia that is not positive definite or violates the
  triangle inequality of principal moments) and converts to and from ``theta`` in a body frame.
- :class:`PayloadIdentifier` fits ``theta`` and the offset by recursive least squares on the
  contact-free frames it is fed (information form, optionally with a forgetting factor), and
  refuses an answer until the data identify it: the posterior standard deviations of the mass
  and centre of mass must be below tolerances (the sensor must have been turned through enough
  orientations: on a fixed sensor a mass and an ``fz`` offset are one direction).

Example:
    >>> p = Payload(0.5, com=(0.0, 0.0, 0.1))  # a point mass 10 cm along the link's z
    >>> p.params()[:4].tolist()  # m, m c in the link frame
    [0.5, 0.0, 0.0, 0.05]
    >>> Payload(0.5, inertia=np.diag([1.0, 0.1, 0.1]))
    Traceback (most recent call last):
    ...
    torchcontact.errors.InputError: payload inertia violates the triangle inequality ...
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from torchcontact.errors import InputError, TorchContactError

__all__ = [
    "PARAM_NAMES",
    "NotIdentifiableError",
    "Payload",
    "PayloadEstimate",
    "PayloadIdentifier",
]

#: The ten inertial parameters about a body origin, in the regressor's column order (the same
#: tuple as :data:`torchcontact.residual.PARAM_NAMES`, which needs torch; a test keeps them equal).
PARAM_NAMES = ("m", "mcx", "mcy", "mcz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")
_SYM = ((0, 0), (0, 1), (1, 1), (0, 2), (1, 2), (2, 2))  # I entries of params 4..9


class NotIdentifiableError(TorchContactError, RuntimeError):
    """The data so far cannot identify the payload (too little excitation or too few frames)."""


def _vec(x: Any, n: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (n,) or not np.isfinite(a).all():
        raise InputError(f"payload {name} must be {n} finite numbers, got {x!r}")
    return a


def _inertia_about(mass: float, com: np.ndarray, inertia_com: np.ndarray) -> np.ndarray:
    """The parallel-axis theorem to the origin (``spatial.inertia_about`` without torch)."""
    return inertia_com + mass * (com @ com * np.eye(3) - np.outer(com, com))


def _theta(mass: float, com: np.ndarray, inertia_origin: np.ndarray) -> np.ndarray:
    return np.array([mass, *(mass * com), *(inertia_origin[i, j] for i, j in _SYM)])


def _inertia_of(theta: np.ndarray) -> np.ndarray:
    out = np.zeros((3, 3))
    for v, (i, j) in zip(theta[4:10], _SYM, strict=True):
        out[i, j] = out[j, i] = v
    return out


@dataclass(frozen=True)
class Payload:
    """A rigid payload: mass, centre of mass and inertia in the frame of the link it is on.

    Args:
        mass: kg (> 0).
        com: ``(3,)`` centre of mass in the link frame, m.
        inertia: ``(3, 3)`` rotational inertia about the centre of mass, link axes, kg m^2;
            zeros (default) is a point mass, anything else must be positive definite and satisfy
            the triangle inequality (each principal moment at most the sum of the other two).
        link: the link (or frame) it is attached to; None: the runtime's payload link.

    Raises:
        InputError: a non-physical payload (the message says which condition fails).
    """

    mass: float
    com: Any = (0.0, 0.0, 0.0)
    inertia: Any = field(default_factory=lambda: np.zeros((3, 3)))
    link: str | None = None

    def __post_init__(self) -> None:
        m = float(self.mass)
        if not (math.isfinite(m) and m > 0):
            raise InputError(f"payload mass must be > 0 kg, got {self.mass!r}")
        com = _vec(self.com, 3, "com (m)")
        inertia = np.asarray(self.inertia, dtype=np.float64)
        if inertia.shape != (3, 3) or not np.isfinite(inertia).all():
            raise InputError(f"payload inertia must be a finite 3 x 3 matrix, got {self.inertia!r}")
        if not np.allclose(inertia, inertia.T, rtol=0.0, atol=1e-12 * (1 + abs(inertia).max())):
            raise InputError("payload inertia must be symmetric")
        inertia = (inertia + inertia.T) / 2
        if inertia.any():
            ev = np.linalg.eigvalsh(inertia)
            if ev[0] <= 0:
                raise InputError(
                    f"payload inertia is not positive definite (principal moments {ev.tolist()}"
                    " kg m^2); give zeros for a point mass"
                )
            tol = 1e-9 * ev[-1]
            if ev[2] > ev[0] + ev[1] + tol:
                raise InputError(
                    "payload inertia violates the triangle inequality of its principal moments"
                    f" ({ev[2]:.6g} > {ev[0]:.6g} + {ev[1]:.6g} kg m^2): no rigid body has it"
                )
        object.__setattr__(self, "mass", m)
        object.__setattr__(self, "com", com)
        object.__setattr__(self, "inertia", inertia)

    def params(self, R_body_link: Any = None, p_body_link: Any = None) -> np.ndarray:  # noqa: N803
        """``(10,)`` parameters (:data:`PARAM_NAMES`) about a body origin, in body axes.

        Args:
            R_body_link: ``(3, 3)`` rotation of the link frame in the body frame (default eye).
            p_body_link: ``(3,)`` origin of the link frame in the body frame, m (default 0).
        """
        R = np.eye(3) if R_body_link is None else np.asarray(R_body_link, float)
        p = np.zeros(3) if p_body_link is None else np.asarray(p_body_link, float)
        c = R @ self.com + p
        return _theta(self.mass, c, _inertia_about(self.mass, c, R @ self.inertia @ R.T))

    @classmethod
    def from_params(
        cls,
        theta: Any,
        R_body_link: Any = None,  # noqa: N803
        p_body_link: Any = None,
        link: str | None = None,
    ) -> Payload:
        """The payload whose parameters about the body origin are ``theta`` (inverse of above).

        Raises:
            InputError: the parameters are not those of a physical body.
        """
        th = _vec(theta, 10, "parameters")
        R = np.eye(3) if R_body_link is None else np.asarray(R_body_link, float)
        p = np.zeros(3) if p_body_link is None else np.asarray(p_body_link, float)
        m = float(th[0])
        if not m > 0:
            raise InputError(f"payload mass must be > 0 kg, got {m!r}")
        c = th[1:4] / m
        ic = _inertia_of(th) - m * (c @ c * np.eye(3) - np.outer(c, c))
        return cls(m, R.T @ (c - p), R.T @ ic @ R, link)


class PayloadEstimate(NamedTuple):
    """A least-squares fit of the payload.

    Attributes:
        theta: ``(10,)`` parameters about the body origin (:data:`PARAM_NAMES`); with
            ``params="mass+com"`` the inertia entries are those of a point mass at the fitted
            centre of mass.
        offset: ``(6,)`` the fitted sensor offset ``[N; N m]`` (zeros if not fitted).
        mass_std: kg, posterior standard deviation of the mass.
        com_std: ``(3,)`` m, of the centre of mass (body frame).
        frames: frames used.
        sigma: the residual's RMS in units of the noise (1 when the model explains the data).
    """

    theta: np.ndarray
    offset: np.ndarray
    mass_std: float
    com_std: np.ndarray
    frames: int
    sigma: float


class PayloadIdentifier:
    """Recursive least squares of a payload (and the sensor offset) from contact-free frames.

    Each frame adds ``Y`` (the sensor regressor of the payload's body, ``(6, 10)``) and the
    residual ``z = ft - ft_model`` (the reading less the model's prediction *without* the
    payload) to the information matrix ``A += lam^dt Phi^T R^-1 Phi`` and ``b``, with
    ``Phi = [Y, I6]`` (the offset is fitted jointly: it drifts, and the tare before a tool change
    may be stale). :meth:`estimate` solves it; :meth:`identify` also checks it.

    Args:
        params: ``"mass+com"`` (default: 4 parameters, the inertia of a point mass at the fitted
            centre of mass, refined by two fixed-point passes) or ``"full"`` (all 10; needs
            angular accelerations to excite the inertia).
        ft_std: ``(6,)`` noise standard deviations ``[N; N m]`` (weights), or
        ft_cov: ``(6, 6)`` noise covariance.
        offset: fit the sensor offset jointly (default True).
        forgetting: per-frame forgetting factor in (0, 1] (1: keep every frame).
        mass_tol: kg, largest posterior standard deviation of the mass accepted.
        com_tol: m, largest posterior standard deviation of each centre-of-mass component.

    Example:
        >>> rng = np.random.default_rng(0)
        >>> ident = PayloadIdentifier(mass_tol=0.01)
        >>> theta = Payload(0.5, com=(0.0, 0.0, 0.1)).params()
        >>> for _ in range(200):  # random gravity directions in the sensor frame
        ...     g = rng.normal(size=3); g *= 9.81 / np.linalg.norm(g)
        ...     Y = np.zeros((6, 10)); Y[:3, 0] = g
        ...     Y[3:, 1:4] = -np.array([[0, -g[2], g[1]], [g[2], 0, -g[0]], [-g[1], g[0], 0]])
        ...     ident.update(Y, Y @ theta + 0.01 * rng.normal(size=6))
        >>> round(ident.identify().mass, 2)
        0.5
    """

    def __init__(
        self,
        params: str = "mass+com",
        *,
        ft_std: Any = None,
        ft_cov: Any = None,
        offset: bool = True,
        forgetting: float = 1.0,
        mass_tol: float = 0.01,
        com_tol: float = 0.005,
    ) -> None:
        from torchcontact.online.bias import _noise_cov

        if params not in ("mass+com", "full"):
            raise InputError(f"params must be 'mass+com' or 'full', got {params!r}")
        if not 0 < forgetting <= 1:
            raise InputError(f"forgetting must be in (0, 1], got {forgetting!r}")
        if not (mass_tol > 0 and com_tol > 0):
            raise InputError("mass_tol and com_tol must be > 0")
        self.params, self.fit_offset = params, bool(offset)
        self.forgetting, self.mass_tol, self.com_tol = float(forgetting), mass_tol, com_tol
        R = _noise_cov(1, ft_std, ft_cov)[0]
        self._W = np.linalg.inv(R)
        self.reset()

    def reset(self) -> None:
        """Forget every frame (a tool change: start identifying the new payload)."""
        n = 16 if self.fit_offset else 10
        self.A = np.zeros((n, n))
        self.b = np.zeros(n)
        self.c = 0.0  # sum of z^T W z (for the residual)
        self.frames = 0
        self.weight = 0.0  # effective number of frames (with forgetting)

    def update(self, Y: Any, z: Any, use: Any = True) -> None:
        """Add frames.

        Args:
            Y: ``(6, 10)`` or ``(N, 6, 10)`` regressor of the payload's body (sensor frame).
            z: ``(6,)`` or ``(N, 6)`` residual ``ft - ft_model`` without the payload ``[N; N m]``.
            use: bool or ``(N,)``: frames to use (contact-free; non-finite frames are skipped).

        Raises:
            InputError: wrong shapes.
        """
        Y = np.asarray(Y, dtype=np.float64)
        z = np.asarray(z, dtype=np.float64)
        if Y.shape == (6, 10):
            Y, z = Y[None], z.reshape(1, -1)
        if Y.ndim != 3 or Y.shape[1:] != (6, 10) or z.shape != (len(Y), 6):
            raise InputError(f"Y must be (N, 6, 10) and z (N, 6), got {Y.shape} and {z.shape}")
        ok = np.broadcast_to(np.asarray(use, dtype=bool), (len(Y),))
        ok = ok & np.isfinite(Y).all((1, 2)) & np.isfinite(z).all(1)
        Y, z = Y[ok], z[ok]
        n = len(Y)
        if n == 0:
            return
        phi = (
            np.concatenate([Y, np.broadcast_to(np.eye(6), (n, 6, 6))], 2) if self.fit_offset else Y
        )
        lam = self.forgetting
        w = lam ** np.arange(n - 1, -1, -1.0)  # older frames of the batch forgotten more
        Wphi = np.einsum("ij,njk->nik", self._W, phi)
        self.A = lam**n * self.A + np.einsum("n,nji,njk->ik", w, phi, Wphi)
        self.b = lam**n * self.b + np.einsum("n,nji,nj->i", w, Wphi, z)
        self.c = lam**n * self.c + float(np.einsum("n,ni,ij,nj->", w, z, self._W, z))
        self.frames += n
        self.weight = lam**n * self.weight + float(w.sum())

    def _solve(self, free: list[int], fixed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Least squares for the ``free`` unknowns with the others fixed to ``fixed``."""
        A, b = self.A, self.b
        n = len(b)
        rest = [i for i in range(n) if i not in free]
        rhs = b[free] - A[np.ix_(free, rest)] @ fixed[rest]
        Af = A[np.ix_(free, free)]
        scale = np.sqrt(np.maximum(np.diag(Af), 1e-300))
        As = Af / np.outer(scale, scale)  # equilibrated: the check is scale-free
        ev, V = np.linalg.eigh(As)
        if ev[0] <= 1e-12 * max(ev[-1], 1e-300):
            raise NotIdentifiableError(
                f"the payload is not identifiable from these {self.frames} frames: the"
                " information matrix is singular (move the sensor through more orientations;"
                " with params='full' also turn it fast)"
            )
        cov = (V / ev) @ V.T / np.outer(scale, scale)
        x = cov @ rhs
        full = fixed.copy()
        full[free] = x
        return full, cov

    def estimate(self) -> PayloadEstimate:
        """The least-squares payload and offset so far, with their posterior uncertainties.

        Raises:
            NotIdentifiableError: no frames, or a singular information matrix.
        """
        if self.frames == 0:
            raise NotIdentifiableError("no contact-free frames fed to the payload identifier yet")
        n = len(self.b)
        off = list(range(10, n))
        x = np.zeros(n)
        if self.params == "full":
            x, cov = self._solve(list(range(10)) + off, x)
        else:
            # point mass: solve (m, m c) with the inertia about the origin fixed to that of a
            # point mass at the current centre of mass (its terms are small: two passes suffice)
            for _ in range(3):
                x, cov = self._solve([0, 1, 2, 3] + off, x)
                m = x[0]
                c = x[1:4] / m if abs(m) > 1e-9 else np.zeros(3)
                x[4:10] = _theta(m, c, _inertia_about(m, c, np.zeros((3, 3))))[4:10]
        # residual: c - 2 x^T b + x^T A x (weighted sum of squares), per equation
        ssr = max(self.c - 2 * x @ self.b + x @ self.A @ x, 0.0)
        dof = 6 * self.weight - (4 if self.params == "mass+com" else 10) - len(off)
        sigma = math.sqrt(ssr / dof) if dof > 0 else math.inf
        s2 = max(1.0, sigma**2)  # unexplained residual widens the uncertainty
        var_m = cov[0, 0] * s2
        m = x[0]
        c = x[1:4] / m if abs(m) > 1e-9 else np.full(3, np.inf)
        # com = h / m to first order: var(c) = (var h - 2 c cov(h, m) + c^2 var m) / m^2
        var_c = (np.diag(cov)[1:4] - 2 * c * cov[0, 1:4] + c * c * cov[0, 0]) * s2 / (m * m)
        return PayloadEstimate(
            x[:10].copy(), x[10:].copy() if self.fit_offset else np.zeros(6),
            float(math.sqrt(var_m)), np.sqrt(np.maximum(var_c, 0.0)), self.frames, sigma,
        )  # fmt: skip

    def identify(
        self,
        R_body_link: Any = None,  # noqa: N803
        p_body_link: Any = None,
        link: str | None = None,
    ) -> Payload:
        """The identified payload, refused while the data cannot identify it.

        Args:
            R_body_link: ``(3, 3)`` the payload link's frame in the regressor's body frame.
            p_body_link: ``(3,)`` its origin, m.
            link: the link name recorded in the :class:`Payload`.

        Raises:
            NotIdentifiableError: too few frames or too little excitation (the message gives the
                posterior standard deviations against the tolerances), or a non-physical fit.
        """
        est = self.estimate()
        worst = float(np.max(est.com_std))
        if not (est.mass_std <= self.mass_tol and worst <= self.com_tol):
            raise NotIdentifiableError(
                f"the payload is not identified yet ({est.frames} frames): mass"
                f" {est.theta[0]:.4g} +- {est.mass_std:.2g} kg (needs +- {self.mass_tol:g}),"
                f" centre of mass +- {worst:.2g} m (needs +- {self.com_tol:g}); keep moving the"
                " sensor through more orientations without contact"
            )
        try:
            return Payload.from_params(est.theta, R_body_link, p_body_link, link)
        except InputError as e:
            raise NotIdentifiableError(f"the fitted payload is not physical: {e}") from None
