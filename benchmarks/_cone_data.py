"""Held-out multi-contact frames for the cone benchmark, with truth from iDynTree.

iCubGenova04 (icub-models), its left arm F/T sensor ``l_arm_ft``. Each frame has 1 to 4 pure
forces, each at a point drawn uniformly (by area) on the collision mesh of ``l_forearm`` or
``l_hand`` (``torchcontact.meshes``, the triangles' outward normals), pushing inside the cone of
half-angle 0.5 rad around the inward normal. The F/T reading is iDynTree's
``computeExpectedFTSensorsMeasurements`` (``ExtWrenchesAndJointTorquesEstimator``, the contacts
as known wrenches about their points, a fixed ``root_link``), an independent implementation of the
dynamics, plus Robotiq FT 300 datasheet noise (0.1 N, 0.005 N m standard deviation).

Distributions (``magnitude``, ``direction``):

* ``"u2-20"``: ``|f|`` uniform in [2, 20] N; ``"log"``: log-uniform in [0.5, 50] N;
* ``"uniform"``: directions uniform over the cone's solid angle; ``"rim"``: within 0.1 rad of its
  boundary (angle from the axis in [0.4, 0.5] rad, uniform over that solid angle).

Slots: ``l_forearm, l_hand, l_forearm, l_hand`` (``force``), a random subset of K active per
frame, so that one contact lies on either link.
"""

from __future__ import annotations

import math

import numpy as np
import torch

import torchcontact as tc

LINKS = ("l_forearm", "l_hand", "l_forearm", "l_hand")
SENSOR = "l_arm_ft"
HALF_ANGLE = 0.5
#: Robotiq FT 300 datasheet noise (standard deviation): force N, moment N m.
SIGMA_F, SIGMA_M = 0.1, 0.005
MAGNITUDES = ("u2-20", "log")
DIRECTIONS = ("uniform", "rim")


def icub_path() -> str:
    import icub_models

    return str(icub_models.get_model_file("iCubGenova04"))


def noise_covariance(dtype=torch.float64) -> torch.Tensor:
    """The FT 300's ``(6, 6)`` reading covariance (diagonal)."""
    return torch.diag(torch.tensor([SIGMA_F**2] * 3 + [SIGMA_M**2] * 3, dtype=dtype))


class _Surface:
    """Area-weighted sampling of points (and their outward normals) on a link's mesh."""

    def __init__(self, mesh) -> None:
        v = mesh.vertices[mesh.faces]  # (F, 3, 3) link frame
        self.v = v
        self.normals = mesh.face_normals()
        area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
        keep = area > 0
        self.v, self.normals, area = self.v[keep], self.normals[keep], area[keep]
        self.p = area / area.sum()

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        f = rng.choice(len(self.p), size=n, p=self.p)
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        w = np.stack([1 - s, s * (1 - r2), s * r2], -1)
        return np.einsum("nk,nkj->nj", w, self.v[f]), self.normals[f]


def _directions(rng, normals, kind: str) -> np.ndarray:
    """Unit force directions inside the cone around ``-normals``."""
    n = len(normals)
    lo = 0.0 if kind == "uniform" else HALF_ANGLE - 0.1
    c = rng.uniform(math.cos(HALF_ANGLE), math.cos(lo), n)  # uniform over the solid angle
    t = rng.normal(size=(n, 3))
    t -= (t * normals).sum(-1, keepdims=True) * normals
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    return -c[:, None] * normals + np.sqrt(1 - c**2)[:, None] * t


def _magnitudes(rng, n: int, kind: str) -> np.ndarray:
    if kind == "u2-20":
        return rng.uniform(2.0, 20.0, n)
    return np.exp(rng.uniform(math.log(0.5), math.log(50.0), n))


class IDynTreeFT:
    """iDynTree's expected F/T readings of known contact forces (fixed root_link)."""

    def __init__(self, path: str, model: tc.RobotModel) -> None:
        import idyntree.swig as idt

        self.idt = idt
        self.est = idt.ExtWrenchesAndJointTorquesEstimator()
        assert self.est.loadModelAndSensorsFromFileWithSpecifiedDOFs(path, list(model.joint_names))
        self.m = self.est.model()
        sens = self.est.sensors()
        T = idt.SIX_AXIS_FORCE_TORQUE
        names = [sens.getSensor(T, i).getName() for i in range(sens.getNrOfSensors(T))]
        self.index = names.index(SENSOR)
        self.sens = sens
        self.root = self.m.getFrameIndex("root_link")
        self.links = {lk: self.m.getLinkIndex(lk) for lk in set(LINKS)}

    def reading(self, q, qd, qdd, contacts) -> np.ndarray:
        """``l_arm_ft``'s reading ``(6,)``; ``contacts``: (link, point (3,), force (3,))."""
        idt = self.idt
        assert self.est.updateKinematicsFromFixedBase(
            idt.JointPosDoubleArray.FromPython(q), idt.JointDOFsDoubleArray.FromPython(qd),
            idt.JointDOFsDoubleArray.FromPython(qdd), self.root,
            idt.Vector3.FromPython([0.0, 0.0, -9.81]),
        )  # fmt: skip
        u = idt.LinkUnknownWrenchContacts(self.m)
        u.clear()
        assert u.addNewUnknownFullWrenchInFrameOrigin(self.m, self.root)
        for link, p, f in contacts:
            c = idt.UnknownWrenchContact()
            c.unknownType = idt.NO_UNKNOWNS
            c.contactPoint = idt.Position.FromPython(np.asarray(p, float))
            c.knownWrench = idt.Wrench.FromPython(np.concatenate([f, np.zeros(3)]))
            u.addNewContactForLink(self.links[link], c)
        meas = idt.SensorsMeasurements(self.sens)
        cw, tau = idt.LinkContactWrenches(self.m), idt.JointDOFsDoubleArray(self.m)
        assert self.est.computeExpectedFTSensorsMeasurements(u, meas, cw, tau)
        w = idt.Wrench()
        assert meas.getMeasurement(idt.SIX_AXIS_FORCE_TORQUE, self.index, w)
        return w.toNumPy().copy()


def make_frames(
    model: tc.RobotModel,
    n: int,
    seed: int = 0,
    magnitude: str = "u2-20",
    direction: str = "uniform",
    counts: tuple[int, ...] = (1, 2, 3, 4),
    noise: bool = True,
) -> dict:
    """``n`` frames (contact counts cycled over ``counts``) and their noisy readings.

    Returns:
        ``q, qd, qdd (n, nv)``, ``ft`` (``{l_arm_ft: (n, 6)}``), ``contacts`` (:class:`Contacts`
        on :data:`LINKS` with normals and the 0.5 rad cones), ``truth (n, 4, 3)`` forces (link
        frame, 0 on inactive slots), ``count (n,)``.
    """
    from torchcontact.meshes import load_meshes

    rng = np.random.default_rng(seed)
    path = icub_path()
    meshes = load_meshes(model, path, "collision", links=sorted(set(LINKS)))
    surf = {lk: _Surface(meshes.links[lk]) for lk in set(LINKS)}
    ref = IDynTreeFT(path, model)
    nv, K = model.nv, len(LINKS)
    q = rng.uniform(-1, 1, (n, nv))
    qd = rng.uniform(-1, 1, (n, nv))
    qdd = rng.uniform(-1, 1, (n, nv))
    count = np.array([counts[i % len(counts)] for i in range(n)])
    active = np.zeros((n, K), bool)
    for i in range(n):
        active[i, rng.choice(K, size=count[i], replace=False)] = True
    pos = np.zeros((n, K, 3))
    nrm = np.zeros((n, K, 3))
    for k, lk in enumerate(LINKS):
        pos[:, k], nrm[:, k] = surf[lk].sample(rng, n)
    d = _directions(rng, nrm.reshape(-1, 3), direction).reshape(n, K, 3)
    truth = d * _magnitudes(rng, n * K, magnitude).reshape(n, K, 1) * active[..., None]
    ft = np.stack([
        ref.reading(q[i], qd[i], qdd[i],
                    [(LINKS[k], pos[i, k], truth[i, k]) for k in range(K) if active[i, k]])
        for i in range(n)
    ])  # fmt: skip
    if noise:
        ft = ft + rng.normal(size=(n, 6)) * np.array([SIGMA_F] * 3 + [SIGMA_M] * 3)
    t = lambda x: torch.as_tensor(x, dtype=torch.float64)  # noqa: E731
    contacts = tc.Contacts(LINKS, ("force",) * K, t(pos), normals=t(nrm), cone_angle=HALF_ANGLE,
                           active=torch.as_tensor(active))  # fmt: skip
    return {"q": t(q), "qd": t(qd), "qdd": t(qdd), "ft": {SENSOR: t(ft)}, "contacts": contacts,
            "truth": t(truth), "count": count}  # fmt: skip


def subset(frames: dict, idx) -> dict:
    """The frames ``idx`` of :func:`make_frames`' result."""
    idx = torch.as_tensor(idx)
    c = frames["contacts"]
    contacts = tc.Contacts(c.links, c.kinds, c.positions[idx], normals=c.normals[idx],
                           cone_angle=c.cone_angle, active=c.active[idx])  # fmt: skip
    return {"q": frames["q"][idx], "qd": frames["qd"][idx], "qdd": frames["qdd"][idx],
            "ft": {k: v[idx] for k, v in frames["ft"].items()}, "contacts": contacts,
            "truth": frames["truth"][idx], "count": frames["count"][idx.numpy()]}  # fmt: skip
