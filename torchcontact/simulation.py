"""Synthetic robot logs with known contacts and optional unmodeled effects (ground truth).

The simulated robot moves along smooth multi-sine joint trajectories (analytic ``qd``, ``qdd``).
Contacts come in segments: a segment holds 1..``max_contacts`` pure-force contacts at random points
of the contact frames (skin patches), with a force that rises and falls smoothly (a half-sine in
time) along a fixed direction pressing into the patch (the patch's -z within a cone). F/T readings
are predicted by the estimator's own forward model (:meth:`ContactEstimator.predict_ft`) from a
*true* robot that may differ from the nominal model (payload), plus effects the rigid-body model
does not know (offset, drift, cable, noise). See :class:`UnmodeledEffects`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from torchcontact.contacts import Contacts
from torchcontact.errors import InputError
from torchcontact.estimation import ContactEstimator
from torchcontact.meshes import LinkMesh
from torchcontact.model import RobotModel
from torchcontact.spatial import cross

__all__ = ["SimulatedLog", "UnmodeledEffects", "contact_setup", "effect_links", "simulate"]


@dataclass(frozen=True)
class UnmodeledEffects:
    """Effects present in the simulated readings but not in the nominal model.

    Attributes:
        offset: ``(6,)`` constant sensor offset ``[N; N m]``.
        drift: ``(6,)`` thermal drift reached after warm-up, ``[N; N m]``: the offset moves by
            ``drift * (1 - exp(-t / drift_time_constant))``; the logged ``temperature`` follows
            the same curve (25 degC -> 35 degC), as a real sensor's housing would.
        drift_time_constant: s.
        cable_force: N, amplitude of a cable/hose force acting on ``cable_link`` whose tension
            and direction depend nonlinearly on four joint angles ``q_a .. q_d`` of
            ``cable_joints``: ``cable_force * [tanh(2 q_b), sin(q_c) cos(q_a), 0.5 sin(2 q_d)]``
            in the link's frame.
        cable_link: link the cable pulls on (None: the middle body of the sensor's subtree chain,
            :func:`effect_links`).
        cable_joints: the joints the cable tension depends on (None: the four joints nearest to
            ``cable_link`` on its path from the root, then below it; a shorter list is cycled).
        payload_mass: kg of an unmodelled payload rigidly attached to ``payload_link``.
        payload_com: ``(3,)`` payload centre of mass in ``payload_link``'s frame, m.
        payload_link: link carrying the payload (None: the deepest body of the sensor's subtree,
            the end effector).
        noise_std: ``(6,)`` white Gaussian noise on the reading, ``[N; N m]``.
    """

    offset: Sequence[float] = (0.0,) * 6
    drift: Sequence[float] = (0.0,) * 6
    drift_time_constant: float = 120.0
    cable_force: float = 0.0
    cable_link: str | None = None
    cable_joints: Sequence[str] | None = None
    payload_mass: float = 0.0
    payload_com: Sequence[float] = (0.0, 0.0, 0.08)
    payload_link: str | None = None
    noise_std: Sequence[float] = (0.0,) * 6


def effect_links(
    model: RobotModel, sensor: str, effects: UnmodeledEffects
) -> tuple[str, str, tuple[str, ...]]:
    """Where the effects act: ``(payload_link, cable_link, cable_joints)``, defaults resolved.

    Defaults follow the sensor on any robot: the payload on the deepest body of the sensor's
    subtree (the end effector), the cable on the middle body of the subtree (a body at half the
    depth), its tension a function of the joints nearest to that body on its path from the root
    (then those below it), at most four.

    Example:
        >>> import torchcontact as tc
        >>> m = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> effect_links(m, "base_ft", UnmodeledEffects())
        ('hand', 'upper_arm', ('shoulder_yaw', 'shoulder_pitch', 'upper_arm_roll', 'elbow_pitch'))
    """
    sub = model.subtree(model.ft_sensors[sensor].child_body)
    depth = {b: d for d, (s, e) in enumerate(model.levels) for b in range(s, e)}
    deepest = max(sub, key=lambda b: (depth[b], b))
    payload = effects.payload_link or model.body_names[deepest]
    # the chain from the sensor's child body down to the deepest body
    chain = [deepest]
    while chain[-1] != sub[0]:
        chain.append(model.body_parent[chain[-1]])
    chain.reverse()
    cable = effects.cable_link or model.body_names[chain[(len(chain) - 1) // 2]]
    if effects.cable_joints is not None:
        joints = tuple(effects.cable_joints)
    else:
        drives = model.q_to_body.detach().cpu().numpy() != 0  # (nv, nb)
        b = model.frame(cable).body
        path = []
        while b >= 0:
            path.append(b)
            b = model.body_parent[b]
        above = [j for b in reversed(path) for j in np.flatnonzero(drives[:, b])]
        below = [j for b in chain if b not in path for j in np.flatnonzero(drives[:, b])]
        order = list(dict.fromkeys([*above[-4:], *below]))[:4]
        joints = tuple(model.joint_names[j] for j in order)
    unknown = [j for j in joints if j not in model.joint_names]
    if unknown or not joints:
        raise InputError(f"cable_joints {list(joints)}: not joints of {model.name}")
    return payload, cable, joints


@dataclass
class SimulatedLog:
    """Columns of a simulated log (numpy, one row per frame).

    Attributes:
        t_ns: ``(N,)`` int64 time stamps, ns.
        q: ``(N, nv)`` joint positions, rad; ``qd``, ``qdd`` likewise.
        qd: ``(N, nv)`` rad/s.
        qdd: ``(N, nv)`` rad/s^2.
        ft: ``(N, 6)`` simulated reading of ``sensor`` (effects included).
        ft_ideal: ``(N, 6)`` the reading the nominal model predicts with the true contacts.
        contact_link: ``(N, K)`` index into ``links`` of each contact, -1 for no contact.
        contact_position: ``(N, K, 3)`` contact points in the link frame, m.
        contact_force: ``(N, K, 3)`` true contact forces in the link frame, N.
        temperature: ``(N,)`` sensor temperature, degC.
        links: contact frame names.
        sensor: the sensor's name.
        joint_names: ``model.joint_names``.
        extra: more columns by name.
        ft_effects: ``(N, 6)`` the part of ``ft`` the nominal model does not explain apart from the
            noise (offset, drift, cable, payload): what an oracle correction subtracts.
        contact_normal: ``(N, K, 3)`` outward surface normals at the contacts, link frame, or
            None (the skin patches' +z).
    """

    t_ns: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    ft: np.ndarray
    ft_ideal: np.ndarray
    contact_link: np.ndarray
    contact_position: np.ndarray
    contact_force: np.ndarray
    temperature: np.ndarray
    links: tuple[str, ...]
    sensor: str
    joint_names: tuple[str, ...]
    extra: dict = field(default_factory=dict)
    ft_effects: np.ndarray | None = None
    contact_normal: np.ndarray | None = None


def _trajectory(rng, n, nv, dt, speed):
    t = np.arange(n) * dt
    q = np.zeros((n, nv))
    qd = np.zeros((n, nv))
    qdd = np.zeros((n, nv))
    center = np.zeros(nv)
    for j in range(nv):
        for _ in range(3):
            a = rng.uniform(0.1, 0.5) * speed
            w = 2 * np.pi * rng.uniform(0.05, 0.4) * speed
            phi = rng.uniform(0, 2 * np.pi)
            q[:, j] += a * np.sin(w * t + phi)
            qd[:, j] += a * w * np.cos(w * t + phi)
            qdd[:, j] += -a * w * w * np.sin(w * t + phi)
        center[j] = rng.uniform(-0.8, 0.8)
        q[:, j] += center[j]
    return t, q, qd, qdd, center


def _within_limits(model: RobotModel, q, qd, qdd, center) -> None:
    """Keep each joint's motion inside the URDF's position and velocity limits (in place).

    A joint that would leave them has its motion about its centre shrunk and its centre moved
    into the range; joints within their limits are unchanged. Any robot can then be simulated:
    a gripper finger (0.04 m of travel, 0.2 m/s) moves within its range instead of being
    flagged as implausible (status bit 64).
    """
    nv = model.nv
    lim = model.joint_limits
    lower, upper, vel = (
        np.asarray(lim.get(k, np.full(nv, np.inf))) for k in ("lower", "upper", "velocity")
    )
    lower = np.where(np.isfinite(lower), lower, -np.inf)
    for j in range(nv):
        dev = q[:, j] - center[j]
        s, c = 1.0, center[j]
        vmax = np.abs(qd[:, j]).max(initial=0.0)
        if np.isfinite(vel[j]) and vmax > vel[j]:
            s = 0.9 * vel[j] / vmax
        lo, hi = lower[j], upper[j]
        if (c + s * dev).min(initial=c) < lo or (c + s * dev).max(initial=c) > hi:
            span = hi - lo
            margin = 0.05 * span if np.isfinite(span) else 0.0
            c = float(np.clip(c, lo + margin, hi - margin))
            room = min(c - lo, hi - c)
            s *= min(1.0, 0.9 * room / max(np.abs(dev).max(initial=0.0), 1e-12))
        q[:, j] = c + s * dev
        qd[:, j] *= s
        qdd[:, j] *= s


def contact_setup(
    model: RobotModel, sensor: str | None = None, links: Sequence[str] | None = None
) -> tuple[str, tuple[str, ...]]:
    """The F/T sensor and contact links a simulation of ``model`` uses.

    Args:
        model: the robot.
        sensor: an F/T sensor of the robot (default: its first).
        links: contact links or frames, each in the sensor's subtree (default: the skin frames of
            the bundled arm when the robot has them, else every link of the sensor's subtree).

    Returns:
        ``(sensor, links)``.

    Raises:
        InputError: a robot without F/T sensor, an unknown sensor, an unknown link, or a link the
            sensor does not see (outside its subtree).

    Example:
        >>> import torchcontact as tc
        >>> contact_setup(tc.RobotModel.from_urdf(tc.robots.tcarm_path()))
        ('base_ft', ('upper_arm_skin', 'forearm_skin', 'hand_skin'))
    """
    from torchcontact.robots import TCARM_SKIN_FRAMES

    if not model.ft_sensors:
        raise InputError(
            f'{model.name} declares no F/T sensor; add a <sensor type="force_torque"> to its URDF'
        )
    if sensor is None:
        sensor = next(iter(model.ft_sensors))
    elif sensor not in model.ft_sensors:
        raise InputError(
            f"--sensor {sensor}: not an F/T sensor of {model.name} ({list(model.ft_sensors)})"
        )
    region = ContactEstimator(model, [sensor]).region
    if links is None:
        if all(f in model.frames and region[model.frame(f).body] == 0 for f in TCARM_SKIN_FRAMES):
            return sensor, TCARM_SKIN_FRAMES
        links = [n for b, n in enumerate(model.body_names) if region[b] == 0]
        if not links:
            raise InputError(f"sensor {sensor!r} of {model.name} has no link in its subtree")
        return sensor, tuple(links)
    links = tuple(links)
    if not links:
        raise InputError("--contact-links: name at least one link")
    unknown = [n for n in links if n not in model.frames]
    if unknown:
        raise InputError(f"--contact-links {unknown}: not links or frames of {model.name}")
    outside = [n for n in links if region[model.frame(n).body] != 0]
    if outside:
        inside = [n for b, n in enumerate(model.body_names) if region[b] == 0]
        raise InputError(
            f"--contact-links {outside}: outside the subtree of sensor {sensor!r}, which sees"
            f" {inside}"
        )
    return sensor, links


def simulate(
    model: RobotModel,
    frames: int,
    *,
    sensor: str | None = None,
    links: Sequence[str] | None = None,
    rate_hz: float = 100.0,
    seed: int = 0,
    contact_fraction: float = 0.5,
    max_contacts: int = 2,
    force_max: float = 20.0,
    speed: float = 1.0,
    effects: UnmodeledEffects | None = None,
    chunk: int = 65536,
    surface: Mapping[str, LinkMesh] | None = None,
) -> SimulatedLog:
    """Simulate a log of ``frames`` frames with known pure-force contacts.

    Args:
        model: the nominal robot (float64 recommended).
        frames: number of frames.
        sensor: F/T sensor to simulate (default: the model's first).
        links: contact frames (default: the skin frames of the bundled arm when present, else the
            links of the sensor's subtree; see :func:`contact_setup`).
        rate_hz: frame rate, Hz.
        seed: random seed (the log is a deterministic function of the arguments).
        contact_fraction: share of frames inside contact segments.
        max_contacts: most simultaneous contacts in a segment (the slot count K).
        force_max: peak force of a contact, N (each segment draws its peak in [0, force_max]).
        speed: scales joint amplitudes and frequencies.
        effects: unmodeled effects in the readings (None: ideal sensor and model).
        chunk: frames per batched call of the forward model.
        surface: link -> its collision mesh (:func:`torchcontact.meshes.load_meshes`): contacts
            lie on the mesh's surface (uniform over its area) and push within 0.62 rad of the
            inward normal, instead of lying on the skin patches' xy planes; every contact link
            needs a mesh. For logs meant for contact localization.

    Returns:
        :class:`SimulatedLog`.

    Example:
        >>> import torchcontact as tc
        >>> log = simulate(tc.RobotModel.from_urdf(tc.robots.tcarm_path()), 50, seed=1)
        >>> log.ft.shape, log.contact_force.shape
        ((50, 6), (50, 2, 3))
    """
    rng = np.random.default_rng(seed)
    sensor, links = contact_setup(model, sensor, links)
    est = ContactEstimator(model, [sensor])
    K, nv, dt = max_contacts, model.nv, 1.0 / rate_hz
    t, q, qd, qdd, center = _trajectory(rng, frames, nv, dt, speed)
    _within_limits(model, q, qd, qdd, center)

    sampler = None
    if surface is not None:
        bare = [n for n in links if n not in surface]
        if bare:
            raise InputError(f"contact links {bare} have no collision mesh to put contacts on")
        sampler = _SurfaceSampler([surface[n] for n in links])
    # contact segments: alternate free and contact stretches of 0.3-3 s
    contact_link = -np.ones((frames, K), dtype=np.int64)
    position = np.zeros((frames, K, 3))
    normal = np.zeros((frames, K, 3))
    normal[..., 2] = 1.0
    force = np.zeros((frames, K, 3))
    i = 0
    in_contact = rng.random() < contact_fraction
    while i < frames:
        length = max(1, int(rng.uniform(0.3, 3.0) * rate_hz))
        if not in_contact:
            # free stretches are scaled so that contact frames make up contact_fraction
            ratio = (1 - contact_fraction) / max(contact_fraction, 1e-9)
            length = max(1, int(length * ratio))
        e = min(frames, i + length)
        if in_contact:
            for k in range(rng.integers(1, K + 1)):
                li = rng.integers(len(links))
                contact_link[i:e, k] = li
                position[i:e, k] = rng.uniform(-0.03, 0.03, 3) * np.array([1, 1, 0])
                d = np.array([*rng.uniform(-0.5, 0.5, 2), -1.0])
                d /= np.linalg.norm(d)
                if sampler is not None:  # on the mesh, d turned from the patch's -z to -n
                    position[i:e, k], normal[i:e, k], R = sampler.sample(rng, int(li))
                    d = R @ d
                peak = rng.uniform(0, force_max)
                shape = np.sin(np.pi * (np.arange(e - i) + 0.5) / (e - i))
                force[i:e, k] = peak * shape[:, None] * d
        in_contact = not in_contact
        i = e

    fx = effects or UnmodeledEffects()
    for used, link, what in (
        (fx.cable_force, fx.cable_link, "cable_link"),
        (fx.payload_mass, fx.payload_link, "payload_link"),
    ):
        if used and link is not None and link not in model.frames:
            raise InputError(
                f"effects.{what} {link!r} is not a link of {model.name}; name one of its links"
            )
    payload_link, cable_link, cable_joints = effect_links(model, sensor, fx)
    cable_q = [model.joint_names.index(j) for j in cable_joints]
    cable_q = [cable_q[i % len(cable_q)] for i in range(4)]
    true_model = model
    if fx.payload_mass:
        true_model = model.with_point_mass(payload_link, fx.payload_mass, fx.payload_com)
    true_est = ContactEstimator(true_model, [sensor])
    # one slot per contact frame, plus the cable's when there is one
    slots = (*links, cable_link) if fx.cable_force else links
    ft_true = np.zeros((frames, 6))
    ft_ideal = np.zeros((frames, 6))
    for s in range(0, frames, chunk):
        sl = slice(s, min(frames, s + chunk))
        n = sl.stop - sl.start
        tq, tqd, tqdd = (torch.as_tensor(x[sl]) for x in (q, qd, qdd))
        pos = torch.zeros(n, len(slots), 3, dtype=torch.float64)
        wr = torch.zeros(n, len(slots), 6, dtype=torch.float64)
        for k in range(K):  # several contacts on one frame: sum their wrenches about the origin
            for li in range(len(links)):
                on = contact_link[sl, k] == li
                f = torch.as_tensor(force[sl, k] * on[:, None])
                p = torch.as_tensor(position[sl, k] * on[:, None])
                wr[:, li, :3] += f
                wr[:, li, 3:] += cross(p, f)
        ideal = est.predict_ft(
            tq, tqd, tqdd, Contacts(slots, ("known",) * len(slots), pos, wrenches=wr)
        )
        ft_ideal[sl] = ideal[sensor].numpy()
        if fx.cable_force:
            qa, qb, qc, qd_ = (q[sl, j] for j in cable_q)
            cable = fx.cable_force * np.stack(
                [np.tanh(2 * qb), np.sin(qc) * np.cos(qa), 0.5 * np.sin(2 * qd_)], axis=-1
            )
            wr[:, -1, :3] = torch.as_tensor(cable)
        true = true_est.predict_ft(
            tq, tqd, tqdd, Contacts(slots, ("known",) * len(slots), pos, wrenches=wr)
        )
        ft_true[sl] = true[sensor].numpy()
    warm = 1 - np.exp(-t / fx.drift_time_constant)
    ft_clean = ft_true + np.asarray(fx.offset) + warm[:, None] * np.asarray(fx.drift)
    ft = ft_clean + rng.normal(size=(frames, 6)) * np.asarray(fx.noise_std)
    return SimulatedLog(
        t_ns=(t * 1e9).round().astype(np.int64),
        q=q,
        qd=qd,
        qdd=qdd,
        ft=ft,
        ft_ideal=ft_ideal,
        contact_link=contact_link,
        contact_position=position,
        contact_force=force,
        temperature=25.0 + 10.0 * warm,
        links=links,
        sensor=sensor,
        joint_names=model.joint_names,
        ft_effects=ft_clean - ft_ideal,
        contact_normal=None if sampler is None else normal,
    )


class _SurfaceSampler:
    """Points uniform over the area of link meshes, with their outward normals."""

    def __init__(self, meshes: Sequence[LinkMesh]) -> None:
        self.tri = [np.asarray(m.vertices)[np.asarray(m.faces)] for m in meshes]
        self.area = []
        for t in self.tri:
            a = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
            self.area.append(a / a.sum())

    def sample(self, rng: np.random.Generator, link: int) -> tuple[np.ndarray, ...]:
        """``(point, outward normal, R)`` with ``R`` turning +z onto the normal (link frame)."""
        t = self.tri[link][rng.choice(len(self.area[link]), p=self.area[link])]
        a, b = rng.random(2)
        if a + b > 1:
            a, b = 1 - a, 1 - b
        p = t[0] + a * (t[1] - t[0]) + b * (t[2] - t[0])
        n = np.cross(t[1] - t[0], t[2] - t[0])
        n /= np.linalg.norm(n)
        x = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(n, x), n], axis=1)
        return p, n, R
