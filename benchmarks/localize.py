"""Contact localization: validation against truth from iDynTree, and throughput.

**Validation** (issue 24, item 4). Contacts are sampled uniformly over the area of the real
collision meshes of the iCub's left forearm and hand (iCubGenova04 from icub-models; sensor
``l_arm_ft``) and of the panda's hand and fingers (example-robot-data; a wrist F/T sensor
``wrist_ft`` on ``panda_hand_joint``, declared with ``RobotModel.with_ft_sensor`` and, for the
reference, as an iDynTree ``<sensor>`` in a copy of the URDF written to a temporary folder). Each
frame has a random joint state (positions within the limits, velocities and accelerations), one
pure force of a given magnitude pushing within 30 degrees of the inward normal, and the sensor
reading of the truth computed by iDynTree's ``computeExpectedFTSensorsMeasurements`` (a
``NO_UNKNOWNS`` contact at the point), an independent library, not torchcontact's forward model.
White noise is added to the readings: the Robotiq FT 300 datasheet's 0.1 N / 0.005 N m standard
deviation, and 10x that. Reported per force magnitude: median and 95th percentile of the distance
between the localized and the true point (mm, sensor frame, over frames with a point), the share
of frames above the force threshold whose link is right, and the share localized without
ambiguity.

**Contact sequences** (``--sequences``): contacts that persist while the arm moves, to measure
the temporal prior (:meth:`Localizer.localize_sequence`). Each run of ``--run-frames`` frames
(default 50 at 200 Hz: 250 ms, its own time segment) holds one contact at a fixed point of a
link, pushing with a fixed magnitude along a direction fixed in the world frame (the base's; the
link's rotation from pinocchio), while every joint moves sinusoidally (amplitudes 0.05-0.3 rad,
0.3-1 Hz) from a random state; the readings of the truth again from iDynTree at every frame, the
noise independent per frame. Reported: the rate of correct links above the threshold frame by
frame (``localize``) and with the temporal prior (``localize_sequence``), on the same noisy
readings.

**Throughput**: iCub forearm + hand collision meshes, ``Localizer.localize`` end to end (readings
in, localization out) at batch 1e5, with its stages timed apart, against in-process references:
trimesh's own ray casting (``trimesh.ray.ray_triangle``, numpy, on the same lines) and a
brute-force numpy loop over frames (a subset, extrapolated), and Embree (embreex) when
``embreex`` is installed.

Run: ``python benchmarks/localize.py [--frames 2000] [--batch 100000] [--threads 2]
[--figure docs/localize.png] [--sequences 40] [--run-frames 50]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import idyntree.swig as idt  # noqa: E402
from _meta import metadata, rate  # noqa: E402
from robots import ROBOTS  # noqa: E402

import torchcontact as tc  # noqa: E402
from torchcontact.localize import Localizer, embree_available  # noqa: E402
from torchcontact.meshes import load_meshes  # noqa: E402

NOISE = {"datasheet": np.array([0.1] * 3 + [0.005] * 3)}
NOISE["10x datasheet"] = 10 * NOISE["datasheet"]
FORCES = (1.0, 2.0, 5.0, 10.0, 20.0)
THRESHOLD = 0.5  # N, the localizer's force threshold in the validation
PANDA_SENSOR = """  <sensor name="wrist_ft" type="force_torque">
    <parent joint="panda_hand_joint"/>
    <force_torque><frame>child</frame><measure_direction>child_to_parent</measure_direction>
    </force_torque>
  </sensor>
</robot>"""


# ----------------------------------------------------------------------------- setups
def icub_setup():
    path = ROBOTS["icub"]()
    model = tc.RobotModel.from_urdf(path)
    links = ["l_forearm", "l_hand"]
    return dict(
        name="iCub",
        path=path,
        idt_path=path,
        model=model,
        sensor="l_arm_ft",
        links=links,
        meshes=load_meshes(model, path, "collision", links=links),
    )


def panda_setup(tmp: Path):
    path = ROBOTS["panda"]()
    model = tc.RobotModel.from_urdf(path, keep_fixed=["panda_hand_joint"])
    model = model.with_ft_sensor("wrist_ft", "panda_hand_joint", "child", "child_to_parent")
    text = path.read_text()
    idt_path = tmp / "panda_wrist_ft.urdf"  # the same robot with iDynTree's sensor element
    idt_path.write_text(text[: text.rindex("</robot>")] + PANDA_SENSOR)
    links = ["panda_hand", "panda_leftfinger", "panda_rightfinger"]
    return dict(
        name="panda",
        path=path,
        idt_path=idt_path,
        model=model,
        sensor="wrist_ft",
        links=links,
        meshes=load_meshes(model, path, "collision", links=links),
        mimic=[("panda_finger_joint2", "panda_finger_joint1")],
    )


def random_joint_state(model, n, rng):
    lo = np.asarray(model.joint_limits["lower"])
    hi = np.asarray(model.joint_limits["upper"])
    lo = np.where(np.isfinite(lo), lo, -np.pi)
    hi = np.where(np.isfinite(hi), hi, np.pi)
    q = lo + (hi - lo) * rng.uniform(0.1, 0.9, (n, model.nv))
    qd = rng.normal(0, 0.5, (n, model.nv))
    qdd = rng.normal(0, 1.0, (n, model.nv))
    for j, name in enumerate(model.joint_names):
        if "finger" in name:  # a gripper opening within its 4 cm, slowly
            q[:, j], qd[:, j], qdd[:, j] = rng.uniform(0.0, 0.04, n), 0.0, 0.0
    return q, qd, qdd


def sample_contacts(setup, n, rng, magnitude, cone=0.5236):
    """Points uniform over the candidate meshes' area, forces within ``cone`` of -normal.

    Returns ``(link, point, force, outward normal)``, link frames.
    """
    meshes = [setup["meshes"].links[k] for k in setup["links"]]
    tris = [m.vertices[m.faces] for m in meshes]
    areas = np.array([0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]),
                                           axis=1).sum() for t in tris])  # fmt: skip
    link = rng.choice(len(meshes), n, p=areas / areas.sum())
    pos, force, normal = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    for li, t in enumerate(tris):
        idx = np.flatnonzero(link == li)
        a = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
        k = rng.choice(len(t), len(idx), p=a / a.sum())
        u, v = rng.random((2, len(idx)))
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        tk = t[k]
        pos[idx] = (
            tk[:, 0] + u[:, None] * (tk[:, 1] - tk[:, 0]) + v[:, None] * (tk[:, 2] - tk[:, 0])
        )
        nrm = np.cross(tk[:, 1] - tk[:, 0], tk[:, 2] - tk[:, 0])
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        # a direction uniform in the cone about -n
        cos_t = 1 - rng.random(len(idx)) * (1 - np.cos(cone))
        phi = rng.uniform(0, 2 * np.pi, len(idx))
        x = np.cross(nrm, np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        y = np.cross(nrm, x)
        sin_t = np.sqrt(1 - cos_t**2)
        d = -cos_t[:, None] * nrm + sin_t[:, None] * (np.cos(phi)[:, None] * x
                                                      + np.sin(phi)[:, None] * y)  # fmt: skip
        force[idx] = magnitude * d
        normal[idx] = nrm
    return link, pos, force, normal


def winding(points, tri):
    """Generalised winding numbers ``(P,)`` of triangles ``(F, 3, 3)`` (Van Oosterom-Strackee)."""
    a, b, c = (tri[None, :, k] - points[:, None] for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc
           + np.einsum("pfi,pfi->pf", b, c) * la + np.einsum("pfi,pfi->pf", c, a) * lb)  # fmt: skip
    return (2 * np.arctan2(det, den)).sum(-1) / (4 * np.pi)


def on_outer_surface(setup, poses, link, pos, normal):
    """True where a point lies on the outside of the union of the candidate meshes.

    Collision meshes are unions of overlapping parts (the panda finger is four boxes, the iCub's
    forearm and hand overlap at the wrist): a point on a face inside another part cannot be
    touched. Tested by the winding number of a point 0.1 mm outside, against every candidate
    mesh posed in the sensor frame.
    """
    R, p0 = poses
    n = len(link)
    ar = np.arange(n)
    out_s = np.einsum("nij,nj->ni", R[ar, link], pos + 1e-4 * normal) + p0[ar, link]
    w = np.zeros(n)
    for li, name in enumerate(setup["links"]):
        m = setup["meshes"].links[name]
        tri = m.vertices[m.faces]  # link frame
        for i in range(n):  # frame by frame: the mesh moves with q
            t_s = tri @ R[i, li].T + p0[i, li]
            w[i] += winding(out_s[i : i + 1], t_s)[0]
    return w < 0.5


def sample_outer(setup, loc, q, qd, qdd, rng, magnitude):
    """:func:`sample_contacts` redrawn until every point is on the outer surface."""
    n = len(q)
    zeros = {s: torch.zeros(n, 6, dtype=torch.float64) for s in loc.estimator_sensors}
    poses = loc_poses(loc, *(torch.as_tensor(x) for x in (q, qd, qdd)), zeros)
    link, pos, force, normal = sample_contacts(setup, n, rng, magnitude)
    todo = ~on_outer_surface(setup, poses, link, pos, normal)
    rounds = 0
    while todo.any() and rounds < 20:
        idx = np.flatnonzero(todo)
        sub = sample_contacts(setup, len(idx), rng, magnitude)
        for arr, new in zip((link, pos, force, normal), sub, strict=True):
            arr[idx] = new
        sp = (poses[0][idx], poses[1][idx])
        todo[idx] = ~on_outer_surface(setup, sp, link[idx], pos[idx], normal[idx])
        rounds += 1
    return link, pos, force


class IDynTreeFT:
    """iDynTree's expected F/T measurements for known contacts (the reference readings)."""

    def __init__(self, path, model, sensor, mimic=()):
        # mimic joints (torchcontact's non-coordinates) are iDynTree coordinates: (name, leader)
        self.mimic = [(n, model.joint_names.index(lead)) for n, lead in mimic]
        self.est = idt.ExtWrenchesAndJointTorquesEstimator()
        assert self.est.loadModelAndSensorsFromFileWithSpecifiedDOFs(
            str(path), [*model.joint_names, *(n for n, _ in mimic)]
        )
        self.m, self.sens = self.est.model(), self.est.sensors()
        T = idt.SIX_AXIS_FORCE_TORQUE
        names = [self.sens.getSensor(T, i).getName() for i in range(self.sens.getNrOfSensors(T))]
        self.index = names.index(sensor)
        self.root = self.m.getFrameIndex(model.body_names[0])

    def reading(self, q, qd, qdd, link, point, force):
        q, qd, qdd = (np.r_[x, [x[lead] for _, lead in self.mimic]] for x in (q, qd, qdd))
        assert self.est.updateKinematicsFromFixedBase(
            idt.JointPosDoubleArray.FromPython(q), idt.JointDOFsDoubleArray.FromPython(qd),
            idt.JointDOFsDoubleArray.FromPython(qdd), self.root,
            idt.Vector3.FromPython([0.0, 0.0, -9.81]),
        )  # fmt: skip
        u = idt.LinkUnknownWrenchContacts(self.m)
        u.clear()
        assert u.addNewUnknownFullWrenchInFrameOrigin(self.m, self.root)
        c = idt.UnknownWrenchContact()
        c.unknownType = idt.NO_UNKNOWNS
        c.contactPoint = idt.Position.FromPython(point)
        c.knownWrench = idt.Wrench.FromPython(np.r_[force, 0.0, 0.0, 0.0])  # about the point
        li = self.m.getLinkIndex(link)
        assert li >= 0, f"iDynTree has no link {link}"
        u.addNewContactForLink(li, c)
        meas = idt.SensorsMeasurements(self.sens)
        cw, tau = idt.LinkContactWrenches(self.m), idt.JointDOFsDoubleArray(self.m)
        assert self.est.computeExpectedFTSensorsMeasurements(u, meas, cw, tau)
        w = idt.Wrench()
        assert meas.getMeasurement(idt.SIX_AXIS_FORCE_TORQUE, self.index, w)
        return w.toNumPy().copy()


# ----------------------------------------------------------------------------- sequences
class PinRotation:
    """World rotation of links from pinocchio (the scenario's world-fixed force directions)."""

    def __init__(self, path, model, mimic=()):
        import pinocchio as pin

        self.pin = pin
        self.m = pin.buildModelFromUrdf(str(path))
        self.d = self.m.createData()
        pairs = [(n, j) for j, n in enumerate(model.joint_names)]
        pairs += [(n, model.joint_names.index(lead)) for n, lead in mimic]
        self.idx = [
            (self.m.joints[self.m.getJointId(n)].idx_q, j)
            for n, j in pairs
            if self.m.existJointName(n) and self.m.joints[self.m.getJointId(n)].nq == 1
        ]

    def __call__(self, q, link):
        qq = self.pin.neutral(self.m)
        for iq, j in self.idx:
            qq[iq] = q[j]
        self.pin.framesForwardKinematics(self.m, self.d, qq)
        return self.d.oMf[self.m.getFrameId(link)].rotation.copy()


def sequence_scenario(setup, loc, runs, run_frames, rng, magnitude, rate_hz=200.0):
    """``runs`` contact runs of ``run_frames`` frames: joint states, truth, segment starts."""
    model, links = setup["model"], setup["links"]
    rot = PinRotation(setup["path"], model, setup.get("mimic", ()))
    n = runs * run_frames
    t = np.arange(run_frames) / rate_hz
    q, qd, qdd = (np.zeros((n, model.nv)) for _ in range(3))
    q0, _, _ = random_joint_state(model, runs, rng)
    for k in range(runs):
        amp = rng.uniform(0.05, 0.3, model.nv)
        w = 2 * np.pi * rng.uniform(0.3, 1.0, model.nv)
        ph = rng.uniform(0, 2 * np.pi, model.nv)
        arg = w * t[:, None] + ph
        sl = slice(k * run_frames, (k + 1) * run_frames)
        q[sl] = q0[k] + amp * (np.sin(arg) - np.sin(ph))
        qd[sl] = amp * w * np.cos(arg)
        qdd[sl] = -amp * w**2 * np.sin(arg)
    for j, name in enumerate(model.joint_names):
        if "finger" in name:  # the gripper holds its opening
            q[:, j] = np.repeat(q0[:, j], run_frames)
            qd[:, j] = qdd[:, j] = 0.0
    lo = np.asarray(model.joint_limits["lower"])
    hi = np.asarray(model.joint_limits["upper"])
    q = np.clip(q, np.where(np.isfinite(lo), lo, -np.inf), np.where(np.isfinite(hi), hi, np.inf))
    zeros = {s: torch.zeros(n, 6, dtype=torch.float64) for s in loc.estimator_sensors}
    R, p0 = loc_poses(loc, *(torch.as_tensor(x) for x in (q, qd, qdd)), zeros)
    link = np.zeros(runs, np.int64)
    pos, f0 = np.zeros((runs, 3)), np.zeros((runs, 3))
    todo = np.ones(runs, bool)
    for _ in range(30):  # the point on the outer surface at every frame of its run
        idx = np.flatnonzero(todo)
        if not len(idx):
            break
        lk, ps, fc, nr = sample_contacts(setup, len(idx), rng, magnitude)
        link[idx], pos[idx], f0[idx] = lk, ps, fc
        for i, k in enumerate(idx):
            fr = np.arange(k * run_frames, (k + 1) * run_frames)
            ok = on_outer_surface(setup, (R[fr], p0[fr]), np.full(run_frames, lk[i]),
                                  np.repeat(ps[i : i + 1], run_frames, 0),
                                  np.repeat(nr[i : i + 1], run_frames, 0))  # fmt: skip
            todo[k] = not ok.all()
    keep = ~todo  # runs still inside another part after 30 draws are dropped
    frame_link = np.repeat(link, run_frames)
    frame_pos = np.repeat(pos, run_frames, 0)
    force = np.zeros((n, 3))
    for k in range(runs):  # the direction fixed in the world from the run's first frame
        i0 = k * run_frames
        d_w = rot(q[i0], links[link[k]]) @ f0[k]
        for i in range(i0, i0 + run_frames):
            force[i] = rot(q[i], links[link[k]]).T @ d_w
    frames = np.flatnonzero(np.repeat(keep, run_frames))
    starts = np.zeros(n, bool)
    starts[::run_frames] = True
    sel = (q[frames], qd[frames], qdd[frames], frame_link[frames], frame_pos[frames],
           force[frames], starts[frames], (R[frames], p0[frames]))  # fmt: skip
    return sel


def validate_sequences(setup, runs, run_frames, rng, friction=1.0):
    """Correct-link rates frame by frame and with the temporal prior, on contact runs."""
    model, sensor, links = setup["model"], setup["sensor"], setup["links"]
    ref = IDynTreeFT(setup["idt_path"], model, sensor, setup.get("mimic", ()))
    loc = Localizer(model, setup["meshes"], links=links, sensors=[sensor],
                    force_threshold=THRESHOLD, friction=friction)  # fmt: skip
    rows = []
    for mag in FORCES[2:]:
        q, qd, qdd, link, pos, force, starts, (R, p0) = sequence_scenario(
            setup, loc, runs, run_frames, rng, mag
        )
        n = len(q)
        ft = np.stack([ref.reading(q[i], qd[i], qdd[i], links[link[i]], pos[i], force[i])
                       for i in range(n)])  # fmt: skip
        tq, tqd, tqdd = (torch.as_tensor(x) for x in (q, qd, qdd))
        ar = np.arange(n)
        true_s = np.einsum("nij,nj->ni", R[ar, link], pos) + p0[ar, link]
        for noise_name, std in NOISE.items():
            noisy = {sensor: torch.as_tensor(ft + rng.normal(size=ft.shape) * std)}
            row = dict(robot=setup["name"], force=mag, noise=noise_name, frames=n,
                       runs=int(starts.sum()))  # fmt: skip
            for mode in ("frame", "prior"):
                if mode == "frame":
                    r = loc.localize(tq, tqd, tqdd, noisy)[sensor]
                else:
                    r = loc.localize_sequence(tq, tqd, tqdd, noisy,
                                              starts=torch.as_tensor(starts))[sensor]  # fmt: skip
                got, code = r.link.numpy(), r.status.numpy()
                above = np.linalg.norm(r.wrench.numpy()[:, :3], axis=1) >= THRESHOLD
                has = np.flatnonzero(got >= 0)
                est_s = np.einsum("nij,nj->ni", R[has, got[has]], r.position.numpy()[has]) + p0[
                    has, got[has]]  # fmt: skip
                err = np.linalg.norm(est_s - true_s[has], axis=1) * 1e3
                row[f"correct_{mode}"] = float((got[above] == link[above]).mean())
                row[f"correct_ok_{mode}"] = _share(got == link, above & (code == 0))
                row[f"flagged_{mode}"] = float((code[above] != 0).mean())
                row[f"median_{mode}"] = float(np.median(err)) if len(err) else np.nan
                row[f"ambiguous_{mode}"] = float(((code[above] & 16) != 0).mean())
                row[f"prior_{mode}"] = float(((code[above] & 256) != 0).mean())
                wrong = above & (got != link)
                several = (code & (16 | 256)) != 0
                row[f"miss_{mode}"] = tuple(
                    int(x.sum())
                    for x in (wrong & (got < 0), wrong & (got >= 0) & several,
                              wrong & (got >= 0) & ~several)
                )  # fmt: skip
            rows.append(row)
    return rows


def print_sequences(rows, run_frames):
    print(
        f"\nContact sequences: runs of {run_frames} frames at 200 Hz, the arm moving, one"
        " contact per run (truth: iDynTree); rates over the frames above the threshold"
    )
    print("| robot | force (N) | noise | frames (runs) | correct link, frame by frame |"
          " correct link, temporal prior | correct among status 0, frame / prior |"
          " flagged (status != 0), frame / prior | ambiguous left | resolved by the prior |"
          " median error (mm), frame by frame / prior | misses: no point / several entries /"
          " one entry, frame by frame; prior |")  # fmt: skip
    print("| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(
            f"| {r['robot']} | {r['force']:g} | {r['noise']} | {r['frames']} ({r['runs']}) |"
            f" {100 * r['correct_frame']:.1f} % | {100 * r['correct_prior']:.1f} % |"
            f" {100 * r['correct_ok_frame']:.1f} / {100 * r['correct_ok_prior']:.1f} % |"
            f" {100 * r['flagged_frame']:.1f} / {100 * r['flagged_prior']:.1f} % |"
            f" {100 * r['ambiguous_prior']:.1f} % | {100 * r['prior_prior']:.1f} % |"
            f" {r['median_frame']:.2f} / {r['median_prior']:.2f} |"
            f" {'/'.join(map(str, r['miss_frame']))}; {'/'.join(map(str, r['miss_prior']))} |"
        )


# ----------------------------------------------------------------------------- validation
def validate(setup, frames, rng, friction=1.0):
    model, sensor, links = setup["model"], setup["sensor"], setup["links"]
    ref = IDynTreeFT(setup["idt_path"], model, sensor, setup.get("mimic", ()))
    loc = Localizer(model, setup["meshes"], links=links, sensors=[sensor],
                    force_threshold=THRESHOLD, friction=friction)  # fmt: skip
    est = tc.ContactEstimator(model, [sensor])
    rows, check = [], 0.0
    for mag in FORCES:
        q, qd, qdd = random_joint_state(model, frames, rng)
        link, pos, force = sample_outer(setup, loc, q, qd, qdd, rng, mag)
        ft = np.stack([ref.reading(q[i], qd[i], qdd[i], links[link[i]], pos[i], force[i])
                       for i in range(frames)])  # fmt: skip
        tq, tqd, tqdd = (torch.as_tensor(x) for x in (q, qd, qdd))
        if mag == FORCES[0]:  # the two forward models agree (torchcontact vs iDynTree)
            w = torch.zeros(frames, len(links), 6, dtype=torch.float64)
            p = torch.zeros(frames, len(links), 3, dtype=torch.float64)
            w[np.arange(frames), link, :3] = torch.as_tensor(force)
            p[np.arange(frames), link] = torch.as_tensor(pos)
            pred = est.predict_ft(tq, tqd, tqdd, tc.Contacts(links, ["known"] * len(links), p,
                                                             wrenches=w))[sensor]  # fmt: skip
            check = float((pred - torch.as_tensor(ft)).abs().max())
        # the true point in the sensor frame (to measure errors across links)
        poses = loc_poses(loc, tq, tqd, tqdd, {sensor: torch.as_tensor(ft)})
        R, p0 = poses
        true_s = np.einsum("nij,nj->ni", R[np.arange(frames), link], pos) + p0[np.arange(frames),
                                                                                 link]  # fmt: skip
        for noise_name, std in NOISE.items():
            noisy = ft + rng.normal(size=ft.shape) * std
            cov = torch.as_tensor(np.diag(std**2))
            r = loc.localize(tq, tqd, tqdd, {sensor: torch.as_tensor(noisy)},
                             ft_covariance={sensor: cov})[sensor]  # fmt: skip
            got = r.link.numpy()
            has = got >= 0
            est_s = np.full((frames, 3), np.nan)
            gi = np.flatnonzero(has)
            est_s[gi] = np.einsum("nij,nj->ni", R[gi, got[gi]], r.position.numpy()[gi]) + p0[
                gi, got[gi]]  # fmt: skip
            err = np.linalg.norm(est_s - true_s, axis=1) * 1e3
            above = np.linalg.norm(r.wrench.numpy()[:, :3], axis=1) >= THRESHOLD
            rows.append(dict(
                robot=setup["name"], force=mag, noise=noise_name, frames=frames,
                found=float(has[above].mean()) if above.any() else np.nan,
                median_mm=float(np.nanmedian(err[has])) if has.any() else np.nan,
                p95_mm=float(np.nanpercentile(err[has], 95)) if has.any() else np.nan,
                correct_link=float((got[above] == link[above]).mean()) if above.any() else np.nan,
                unambiguous=float((r.status.numpy()[above] == 0).mean()) if above.any() else np.nan,
                correct_ok=_share(got == link, above & (r.status.numpy() == 0)),
                correct_flagged=_share(got == link, above & (r.status.numpy() != 0)),
                std_mm=float(np.nanmedian(r.position_std.numpy()[has]) * 1e3) if has.any()
                else np.nan,
                errors=err[has],
                choice=likelihood_choice(setup, loc, r, R, p0, link, std, above),
            ))  # fmt: skip
    return rows, check


def entries(mesh, o, d, merge=1e-3):
    """Every point where the line ``o + t d`` enters ``mesh`` (link frame): ``(t, cos)`` arrays.

    Numpy Moller-Trumbore over all faces (the reference of the choice below, not the
    localizer's casting); ``cos`` is ``d . n`` (< 0: entering); hits closer than ``merge`` along
    the line (an edge or vertex met twice) are one entry.
    """
    tri = mesh.vertices[mesh.faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.cross(e1, e2)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    pv = np.cross(d, e2)
    det = np.einsum("fi,fi->f", e1, pv)
    ok = np.abs(det) > 1e-15
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = o - tri[:, 0]
    u = np.einsum("fi,fi->f", tv, pv) * inv
    qv = np.cross(tv, e1)
    v = (qv @ d) * inv
    t = np.einsum("fi,fi->f", e2, qv) * inv
    cos = n @ d
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (cos < 0)
    order = np.argsort(t[hit])
    ts, cs = t[hit][order], cos[hit][order]
    keep = np.r_[True, np.diff(ts) > merge] if len(ts) else np.zeros(0, bool)
    return ts[keep], cs[keep]


def likelihood_choice(setup, loc, r, R, p0, link, std, above):
    """On the ambiguous frames: the first entry (the localizer's) vs a likelihood choice.

    Per frame with several entries (status bit 16), every entry ``c`` of every candidate link
    is scored by the Mahalanobis distance of the wrench a pure force at ``c`` best explains
    (weighted least squares with the F/T covariance ``diag(std^2)``), alone and with the prior
    of a contact uniform over the surface area (the line density ``1 / |cos|`` of the entry's
    angle). Returns the correct-link rates on those frames: first entry, min distance, min
    distance with the prior, and the share where the true link is among the entries at all.
    """
    code, got = r.status.numpy(), r.link.numpy()
    W = r.wrench.numpy()
    Winv = 1.0 / std**2
    amb = np.flatnonzero(above & ((code & 16) != 0))
    first, dist, post, oracle = [], [], [], []
    meshes = [setup["meshes"].links[name] for name in setup["links"]]
    for i in amb:
        f, m = W[i, :3], W[i, 3:]
        a, u = np.cross(f, m) / (f @ f), f / np.linalg.norm(f)
        cands = []
        for li, mesh in enumerate(meshes):
            o = R[i, li].T @ (a - p0[i, li] - u)  # a point 1 m behind a on the line
            d = R[i, li].T @ u
            for t, c in zip(*entries(mesh, o, d), strict=True):
                cands.append((li, a + u * (t - 1.0), c))
        if not cands:
            continue
        scores = []
        for _li, c, cos in cands:
            A = np.r_[np.eye(3), np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])]
            fh = np.linalg.solve(A.T @ (A * Winv[:, None]), A.T @ (W[i] * Winv))
            res = W[i] - A @ fh
            d2 = float(res @ (res * Winv))
            scores.append((d2, d2 / 2 + np.log(abs(cos))))
        scores = np.array(scores)
        links = [li for li, _, _ in cands]
        first.append(got[i] == link[i])
        dist.append(links[int(np.argmin(scores[:, 0]))] == link[i])
        post.append(links[int(np.argmin(scores[:, 1]))] == link[i])
        oracle.append(link[i] in links)
    if not first:
        return (np.nan,) * 4 + (0,)
    return (*(float(np.mean(x)) for x in (first, dist, post, oracle)), len(first))


def _share(hit: np.ndarray, among: np.ndarray) -> float:
    """The share of ``hit`` among the frames ``among`` (NaN when there are none)."""
    return float(hit[among].mean()) if among.any() else np.nan


def loc_poses(loc, q, qd, qdd, ft):
    """``R_sensor_link (N, L, 3, 3)``, ``p_sensor_link (N, L, 3)`` from the line program."""
    from torchcontact.kernels.runner import run_program as _run
    from torchcontact.localize import line_program

    prog = line_program(loc.em, list(range(len(loc.links))), False)
    tensors = {"q": q, "qd": qd, "qdd": qdd}
    tensors.update({f"ft{i}": ft[s] for i, s in enumerate(loc.estimator_sensors)})
    out = _run(prog, tensors, "auto", None)
    pose = out["pose"].reshape(q.shape[0], len(loc.links), 12).numpy()
    return pose[..., :9].reshape(q.shape[0], -1, 3, 3), pose[..., 9:]


def print_validation(rows, checks):
    print("\nValidation: readings of the truth from iDynTree's expected F/T measurements")
    for name, c in checks.items():
        print(f"  {name}: torchcontact predict_ft vs iDynTree, max |diff| = {c:.1e} (N, N m)")
    print(
        "| robot | force (N) | noise | frames | median error (mm) | p95 (mm) | correct link |"
        " unambiguous (status 0) | correct link among status 0 | flagged (status != 0) |"
        " correct link among flagged | found | predicted std (mm, median) |"
    )
    print("| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
          " ---: |")  # fmt: skip
    for r in rows:
        print(
            f"| {r['robot']} | {r['force']:g} | {r['noise']} | {r['frames']} |"
            f" {r['median_mm']:.2f} | {r['p95_mm']:.1f} | {100 * r['correct_link']:.1f} % |"
            f" {100 * r['unambiguous']:.1f} % | {100 * r['correct_ok']:.1f} % |"
            f" {100 * (1 - r['unambiguous']):.1f} % | {100 * r['correct_flagged']:.1f} % |"
            f" {100 * r['found']:.1f} % | {r['std_mm']:.2f} |"
        )


def print_choice(rows):
    print(
        "\nAmbiguous frames (status bit 16, above the threshold): which entry to report."
        " Correct link with the first entry (the localizer's rule), with the entry whose pure"
        " force best explains the wrench (Mahalanobis distance, F/T covariance), with that and"
        " the prior of contacts uniform over the area; and the share of frames whose true link"
        " is among the entries"
    )
    print("| robot | force (N) | noise | ambiguous frames | first entry | min distance |"
          " min distance + area prior | true link among the entries |")  # fmt: skip
    print("| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        first, dist, post, oracle, n = r["choice"]
        if n:
            print(f"| {r['robot']} | {r['force']:g} | {r['noise']} | {n} | {100 * first:.1f} % |"
                  f" {100 * dist:.1f} % | {100 * post:.1f} % | {100 * oracle:.1f} % |")  # fmt: skip


def figure(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    robots = list(dict.fromkeys(r["robot"] for r in rows))
    fig, axes = plt.subplots(2, len(robots), figsize=(5.5 * len(robots), 7.5), squeeze=False,
                             gridspec_kw={"height_ratios": [3, 2]})  # fmt: skip
    for col, robot in enumerate(robots):
        ax, ax2 = axes[0, col], axes[1, col]
        for noise, color in zip(NOISE, ("tab:blue", "tab:red"), strict=True):
            rs = [r for r in rows if r["robot"] == robot and r["noise"] == noise]
            f = np.array([r["force"] for r in rs])
            ax.plot(f, [r["median_mm"] for r in rs], "o-", color=color, label=f"{noise}: median")
            ax.plot(f, [r["p95_mm"] for r in rs], "s--", color=color, alpha=0.6,
                    label=f"{noise}: 95th percentile")  # fmt: skip
            ax2.plot(f, [100 * r["correct_link"] for r in rs], "o-", color=color,
                     label=f"{noise}: correct link")  # fmt: skip
            ax2.plot(f, [100 * r["unambiguous"] for r in rs], "^:", color=color, alpha=0.6,
                     label=f"{noise}: unambiguous")  # fmt: skip
        ax.axhline(5.0, color="gray", lw=0.8, ls=":")
        ax2.axhline(99.0, color="gray", lw=0.8, ls=":")
        for a in (ax, ax2):
            a.axvline(5.0, color="gray", lw=0.8, ls=":")
            a.set_xscale("log")
            a.set_xticks(FORCES, [f"{x:g}" for x in FORCES])
            a.grid(True, which="both", alpha=0.3)
            a.legend(fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel("localization error (mm)")
        ax.set_title(f"{robot}: single contact from the F/T wrench (truth: iDynTree)")
        ax2.set_xlabel("contact force (N)")
        ax2.set_ylabel("frames above threshold (%)")
        ax2.set_ylim(0, 101)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"\nfigure: {path}")


# ----------------------------------------------------------------------------- throughput
def throughput(batch, threads, rng):
    setup = icub_setup()
    model, sensor, links = setup["model"], setup["sensor"], setup["links"]
    meshes = setup["meshes"]
    ntri = sum(len(meshes.links[k].faces) for k in links)
    q, qd, qdd = random_joint_state(model, batch, rng)
    link, pos, force, _ = sample_contacts(setup, batch, rng, 5.0)
    est = tc.ContactEstimator(model, [sensor])
    tq, tqd, tqdd = (torch.as_tensor(x) for x in (q, qd, qdd))
    w = torch.zeros(batch, len(links), 6, dtype=torch.float64)
    p = torch.zeros(batch, len(links), 3, dtype=torch.float64)
    w[np.arange(batch), link, :3] = torch.as_tensor(force)
    p[np.arange(batch), link] = torch.as_tensor(pos)
    ft = est.predict_ft(tq, tqd, tqdd, tc.Contacts(links, ["known"] * 2, p, wrenches=w),
                        backend="cpu")  # fmt: skip
    print(
        f"\nThroughput: iCub l_forearm + l_hand collision meshes ({ntri} triangles), batch"
        f" {batch}, {threads} thread(s)"
    )
    print("| method | dtype | frames/s | ratio to trimesh | spread (IQR/median) |")
    print("| --- | --- | ---: | ---: | ---: |")
    results = {}
    loc64 = Localizer(model, meshes, links=links, sensors=[sensor], backend="cpu")
    # the rays of the batch, for the references (the same lines in the links' frames)
    R, p0 = loc_poses(loc64, tq[:2000], tqd[:2000], tqdd[:2000], {sensor: ft[sensor][:2000]})
    r64 = loc64.localize(tq[:2000], tqd[:2000], tqdd[:2000], {sensor: ft[sensor][:2000]})[sensor]
    b = r64.wrench.numpy()
    f, m = b[:, :3], b[:, 3:]
    a = np.cross(f, m) / (f * f).sum(1, keepdims=True)
    u = f / np.linalg.norm(f, axis=1, keepdims=True)
    orig = np.einsum("nlji,nlj->nli", R, a[:, None] - p0)
    dirs = np.einsum("nlji,nj->nli", R, u)
    n_ref = 2000
    import trimesh

    tm = [trimesh.Trimesh(meshes.links[k].vertices, meshes.links[k].faces, process=False)
          for k in links]  # fmt: skip

    def trimesh_cast():
        for li, mesh in enumerate(tm):
            inter = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
            inter.intersects_location(
                orig[:, li] - 1.0 * dirs[:, li], dirs[:, li], multiple_hits=True
            )

    t0 = time.perf_counter()
    trimesh_cast()
    ref_rate = n_ref / (time.perf_counter() - t0)
    results["trimesh ray_triangle (numpy), rays only"] = ref_rate
    print(
        f"| trimesh `ray_triangle` (numpy + rtree), rays only, {n_ref} frames | float64 |"
        f" {ref_rate:,.0f} | 1.0x | - |"
    )

    def numpy_loop(k=200):
        for i in range(k):
            for li in range(len(links)):
                v = meshes.links[links[li]].vertices
                fc = meshes.links[links[li]].faces
                e1, e2 = v[fc[:, 1]] - v[fc[:, 0]], v[fc[:, 2]] - v[fc[:, 0]]
                pv = np.cross(dirs[i, li], e2)
                det = (e1 * pv).sum(1)
                tv = orig[i, li] - v[fc[:, 0]]
                uu = (tv * pv).sum(1) / det
                qv = np.cross(tv, e1)
                vv = (qv * dirs[i, li]).sum(1) / det
                _ = (uu >= 0) & (vv >= 0) & (uu + vv <= 1)

    t0 = time.perf_counter()
    numpy_loop()
    np_rate = 200 / (time.perf_counter() - t0)
    print(
        f"| numpy loop over frames, every triangle, rays only, 200 frames | float64 |"
        f" {np_rate:,.0f} | {np_rate / ref_rate:.2f}x | - |"
    )
    for dtype in (torch.float64, torch.float32):
        mdl = model.to(dtype=dtype)
        loc = Localizer(mdl, meshes, links=links, sensors=[sensor], backend="cpu", ray="torch")
        ins = [x.to(dtype) for x in (tq, tqd, tqdd)]
        fts = {sensor: ft[sensor].to(dtype)}
        loc.localize(*(x[:100] for x in ins), {sensor: fts[sensor][:100]})  # build the kernel
        kernels_wait()
        rt, iqr = rate(lambda loc=loc, ins=ins, fts=fts: loc.localize(*ins, fts), batch, 2.0)
        name = "torchcontact `Localizer.localize`, tree traversal (torch), end to end"
        print(f"| {name} | {str(dtype)[6:]} | {rt:,.0f} | {rt / ref_rate:.1f}x | {iqr:.2f} |")
        results[f"torch {dtype}"] = rt
        # what bounds it: the stages apart
        stage_times(loc, ins, fts, sensor, dtype)
    sub = 4000
    locb = Localizer(model, meshes, links=links, sensors=[sensor], backend="cpu", ray="brute")
    ins = (tq[:sub], tqd[:sub], tqdd[:sub])
    rt, iqr = rate(lambda: locb.localize(*ins, {sensor: ft[sensor][:sub]}), sub, 1.0)
    print(
        f'| torchcontact, every triangle (`ray="brute"`, torch), {sub} frames | float64 |'
        f" {rt:,.0f} | {rt / ref_rate:.1f}x | {iqr:.2f} |"
    )
    if embree_available():
        loce = Localizer(model, meshes, links=links, sensors=[sensor], backend="cpu", ray="embree")
        ins = (tq, tqd, tqdd)
        # on an oversubscribed machine, torch's second thread waits for a core at every op:
        # the one-thread row says how much (interleaved, same process)
        for nt in dict.fromkeys((threads, 1)):
            torch.set_num_threads(nt)
            rt, iqr = rate(lambda: loce.localize(*ins, {sensor: ft[sensor]}), batch, 2.0)
            print(
                '| torchcontact `Localizer.localize` with Embree (`ray="embree"`, embreex),'
                f" end to end, {nt} thread(s) | float64 | {rt:,.0f} |"
                f" {rt / ref_rate:.1f}x | {iqr:.2f} |"
            )
        torch.set_num_threads(threads)
    else:
        print('| Embree (`ray="embree"`) | - | not installed (pip install embreex) | | |')
    return results


def kernels_wait():
    from torchcontact import kernels

    kernels.wait_for_builds()


def stage_times(loc, ins, fts, sensor, dtype):
    """Seconds per 1e5 frames of the line program, the casting and the selection."""
    from torchcontact.kernels.runner import run_program as _run
    from torchcontact.localize import cast_bvh, line_program, select_entries

    n = ins[0].shape[0]
    prog = line_program(loc.em, list(range(len(loc.links))), False)
    tensors = {"q": ins[0], "qd": ins[1], "qdd": ins[2], "ft0": fts[sensor]}
    t0 = time.perf_counter()
    out = _run(prog, tensors, "cpu", None)
    t_prog = time.perf_counter() - t0
    b = out["b"][:, :6]
    f, m = b[:, :3], b[:, 3:]
    L = len(loc.links)
    pose = out["pose"].reshape(n, L, 12)
    R, p = pose[..., :9].reshape(n, L, 3, 3), pose[..., 9:]
    a = torch.linalg.cross(f, m) / (f * f).sum(-1, keepdim=True)
    u = f / f.norm(dim=-1, keepdim=True)
    orig = torch.einsum("nlji,nlj->nli", R, a.unsqueeze(1) - p).reshape(-1, 3)
    dirs = torch.einsum("nlji,nj->nli", R, u).reshape(-1, 3)
    ray_link = torch.arange(L).repeat(n)
    t_cast = []
    for _ in range(3):
        t0 = time.perf_counter()
        hits = cast_bvh(loc.triangles, orig, dirs, ray_link)
        t_cast.append(time.perf_counter() - t0)
    t_cast = float(np.median(t_cast))
    t0 = time.perf_counter()
    select_entries(hits, torch.arange(n).repeat_interleave(L), n, 1e-3, 1e-9)
    t_sel = time.perf_counter() - t0
    print(
        f"|   stages ({str(dtype)[6:]}): line program (kernel) {1e3 * t_prog:.0f} ms, tree"
        f" traversal + ray-triangle {1e3 * t_cast:.0f} ms ({len(hits.ray) / n:.1f} hits/frame),"
        f" selection {1e3 * t_sel:.0f} ms | | | | |"
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=2000, help="validation frames per force")
    ap.add_argument("--batch", type=int, default=100_000, help="throughput batch")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--figure", default=str(Path(__file__).resolve().parents[1] / "docs"
                                            / "localize.png"))  # fmt: skip
    ap.add_argument("--skip-validation", action="store_true")
    ap.add_argument("--skip-throughput", action="store_true")
    ap.add_argument(
        "--sequences",
        type=int,
        default=40,
        help="contact runs per force in the sequence validation (0: skip it)",
    )
    ap.add_argument("--run-frames", type=int, default=50, help="frames per contact run (200 Hz)")
    ap.add_argument(
        "--friction",
        type=float,
        default=1.0,
        help="the localizer's friction coefficient (cone filter of the entries; the truth"
        " pushes within 30 degrees of the normal, mu = 0.577)",
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(metadata())
    rng = np.random.default_rng(0)
    if not args.skip_validation:
        rows, checks = [], {}
        with tempfile.TemporaryDirectory() as tmp:
            for setup in (icub_setup(), panda_setup(Path(tmp))):
                r, c = validate(setup, args.frames, rng, args.friction)
                rows += r
                checks[setup["name"]] = c
        print_validation(rows, checks)
        print_choice(rows)
        figure(rows, args.figure)
    if args.sequences:
        rows = []
        with tempfile.TemporaryDirectory() as tmp:
            for setup in (icub_setup(), panda_setup(Path(tmp))):
                rows += validate_sequences(
                    setup, args.sequences, args.run_frames, rng, args.friction
                )
        print_sequences(rows, args.run_frames)
    if not args.skip_throughput:
        throughput(args.batch, args.threads, rng)


if __name__ == "__main__":
    main()
