"""Localization in the single-frame ONNX runtime: latency of the one-link graph and of the step.

:func:`torchcontact.onnx.step.localize.onnx_single_link` builds stages 2-4 of the localization
for one candidate link as an ONNX graph (every face tested at once). This script runs it with
onnxruntime, one frame per call as the live loop does, on the iCub's l_hand collision mesh, its
convex hull and a 12-face box, checks its point against ``Localizer`` (float64, same frames),
and times it against the torch path's per-call latency (``Localizer.localize_wrench`` for one
frame) in the same process.

The second table is what ``export estimator --localize l_hand`` adds to the iCub left arm's
single-frame estimator (sensor l_arm_ft, slots l_hand:force and l_forearm:force): p50 of
:meth:`EstimatorRuntime.step` with and without the localization, the two runtimes called in
turn in one process (so load affects both alike), on frames whose contact is localized.

Run: ``python benchmarks/localize_onnx.py [--calls 2000]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _meta import metadata  # noqa: E402
from robots import ROBOTS  # noqa: E402

import torchcontact as tc  # noqa: E402
from torchcontact.localize import Localizer  # noqa: E402
from torchcontact.meshes import LinkMesh, load_meshes  # noqa: E402
from torchcontact.onnx.step.localize import onnx_single_link  # noqa: E402


def frames(mesh: LinkMesh, n: int, rng):
    """Wrenches of pushes on the mesh (sensor frame = link frame rotated and shifted)."""
    tri = mesh.vertices[mesh.faces]
    k = rng.integers(len(tri), size=n)
    w = rng.dirichlet([1, 1, 1], size=n)
    p = np.einsum("nk,nki->ni", w, tri[k])
    nrm = np.cross(tri[k, 1] - tri[k, 0], tri[k, 2] - tri[k, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    f = -(nrm + 0.3 * rng.normal(size=(n, 3))) * 5
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.linalg.det(R)
    t = np.array([0.1, -0.2, 0.3])
    ps, fs = p @ R.T + t, f @ R.T
    return np.c_[fs, np.cross(ps, fs)], R, t


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--calls", type=int, default=2000)
    args = ap.parse_args()
    import onnxruntime as ort
    import trimesh

    torch.set_num_threads(1)
    print(metadata(), "| onnxruntime", ort.__version__)
    path = ROBOTS["icub"]()
    model = tc.RobotModel.from_urdf(path)
    hand = load_meshes(model, path, "collision", links=["l_hand"]).links["l_hand"]
    hull = trimesh.Trimesh(hand.vertices, hand.faces).convex_hull
    box = trimesh.creation.box(extents=(0.05, 0.03, 0.08))
    cases = {
        "iCub l_hand collision mesh": hand,
        "its convex hull": LinkMesh("l_hand", hand.body, np.asarray(hull.vertices),
                                    np.asarray(hull.faces), hand.R_body_link, hand.p_body_link,
                                    None, ("hull",)),
        "box": LinkMesh("l_hand", hand.body, np.asarray(box.vertices), np.asarray(box.faces),
                        hand.R_body_link, hand.p_body_link, None, ("box",)),
    }  # fmt: skip
    rng = np.random.default_rng(0)
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    print(
        "| mesh | faces | ONNX nodes | onnxruntime p50 (us) | p99 (us) | torch per call p50 (us)"
        " | ratio | max |point - Localizer| (m) |"
    )
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for name, mesh in cases.items():
        graph = onnx_single_link(mesh, force_threshold=1.0)
        sess = ort.InferenceSession(graph.SerializeToString(), so,
                                    providers=["CPUExecutionProvider"])  # fmt: skip
        W, R, t = frames(mesh, 200, rng)
        loc = Localizer(model, {"l_hand": mesh}, links=["l_hand"], sensors=["l_arm_ft"])
        Rt = torch.as_tensor(R).expand(len(W), 1, 3, 3)
        pt = torch.as_tensor(t).expand(len(W), 1, 3)
        ref = loc.localize_wrench(torch.as_tensor(W), Rt, pt, "l_arm_ft")
        err = 0.0
        for i in range(len(W)):
            out = sess.run(None, {"wrench": W[i].astype(np.float32),
                                  "R_sensor_link": R.astype(np.float32),
                                  "p_sensor_link": t.astype(np.float32)})  # fmt: skip
            if ref.status[i] in (0, 16):
                err = max(err, float(np.abs(out[0] - ref.position[i].numpy()).max()))
        feeds = {"wrench": W[0].astype(np.float32), "R_sensor_link": R.astype(np.float32),
                 "p_sensor_link": t.astype(np.float32)}  # fmt: skip
        lat = []
        for _ in range(args.calls):
            t0 = time.perf_counter()
            sess.run(None, feeds)
            lat.append(time.perf_counter() - t0)
        tl = []
        w1, R1, p1 = torch.as_tensor(W[:1]), Rt[:1], pt[:1]
        for _ in range(min(args.calls, 500)):
            t0 = time.perf_counter()
            loc.localize_wrench(w1, R1, p1, "l_arm_ft")
            tl.append(time.perf_counter() - t0)
        p50, p99 = np.percentile(lat, 50) * 1e6, np.percentile(lat, 99) * 1e6
        t50 = np.percentile(tl, 50) * 1e6
        print(
            f"| {name} | {len(mesh.faces)} | {len(graph.graph.node)} | {p50:.0f} | {p99:.0f} |"
            f" {t50:.0f} | {t50 / p50:.1f}x | {err:.1e} |"
        )
    step_latency(model, path, cases, args.calls, rng)


def step_latency(model, path: str, cases: dict, calls: int, rng) -> None:
    """p50 of the iCub left arm's step with and without ``--localize l_hand``, in turn."""
    import tempfile

    import onnx

    from torchcontact.export import export_estimator
    from torchcontact.runtime import EstimatorRuntime

    links, kinds = ["l_forearm", "l_hand"], ["force", "force"]
    est = tc.ContactEstimator(model, ["l_arm_ft"])
    mesh = cases["iCub l_hand collision mesh"]
    n = 64
    q = torch.zeros(n, model.nv, dtype=torch.float64)
    tri = mesh.vertices[mesh.faces]
    k = rng.integers(len(tri), size=n)
    pts = np.einsum("nk,nki->ni", rng.dirichlet([1, 1, 1], size=n), tri[k])
    nrm = np.cross(tri[k, 1] - tri[k, 0], tri[k, 2] - tri[k, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    f = -(nrm + 0.3 * rng.normal(size=(n, 3))) * 5
    w = torch.as_tensor(np.c_[f, np.zeros((n, 3))])[:, None]
    c = tc.Contacts(["l_hand"], ["known"], torch.as_tensor(pts)[:, None], wrenches=w)
    ft = est.predict_ft(q, q, q, c)["l_arm_ft"].numpy()
    print()
    print("| step graph (iCub left arm, l_arm_ft) | faces | nodes | step p50 (us) | p99 (us) |"
          " p50 / without | frames localized |")  # fmt: skip
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    with tempfile.TemporaryDirectory() as d:
        runtimes = {}
        plain = f"{d}/plain.onnx"
        export_estimator(model, ["l_arm_ft"], links, kinds, plain, joints="sensed")
        runtimes["without --localize"] = (plain, None)
        for name, m in cases.items():
            out = f"{d}/{len(runtimes)}.onnx"
            export_estimator(model, ["l_arm_ft"], links, kinds, out, joints="sensed",
                             localize="l_hand", meshes={"l_hand": m},
                             localize_max_faces=10_000)  # fmt: skip
            runtimes[f"--localize l_hand: {name}"] = (out, m)
        rts = {k: EstimatorRuntime(p.replace(".onnx", ".step.onnx"), robot=model)
               for k, (p, _) in runtimes.items()}  # fmt: skip
        feeds = [{"q": q[i].numpy(), "qd": q[i].numpy(), "qdd": q[i].numpy(),
                  "ft": ft[i][None], "positions": np.zeros((2, 3)), "active": np.zeros(2)}
                 for i in range(n)]  # fmt: skip
        found = {k: sum(rt.step(x).get("localize_status", 1) == 0 for x in feeds)
                 for k, rt in rts.items()}  # fmt: skip
        lat = {k: [] for k in rts}
        for c_ in range(calls):
            x = feeds[c_ % n]
            for k, rt in rts.items():  # in turn: the load falls on every graph alike
                t0 = time.perf_counter()
                rt.step(x)
                lat[k].append(time.perf_counter() - t0)
        base = np.percentile(lat["without --localize"], 50)
        for k, (p, m) in runtimes.items():
            nodes = len(onnx.load(p.replace(".onnx", ".step.onnx")).graph.node)
            p50, p99 = np.percentile(lat[k], 50), np.percentile(lat[k], 99)
            loc = f"{found[k]}/{n}" if m is not None else "-"
            print(f"| {k} | {len(m.faces) if m is not None else '-'} | {nodes} |"
                  f" {p50 * 1e6:.0f} | {p99 * 1e6:.0f} | {p50 / base:.2f} | {loc} |")  # fmt: skip


if __name__ == "__main__":
    main()
