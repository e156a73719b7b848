"""Localization in the single-frame ONNX runtime: latency of the one-link graph.

:func:`torchcontact.localize.onnx_single_link` builds stages 2-4 of the localization for one
candidate link as an ONNX graph (every face tested at once). This script runs it with onnxruntime,
one frame per call as the live loop does, on the iCub's l_hand collision mesh, its convex hull
and a 12-face box, checks its point against ``Localizer`` (float64, same frames), and times it
against the torch path's per-call latency (``Localizer.localize_wrench`` for one frame) in the
same process.

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
from torchcontact.localize import Localizer, onnx_single_link  # noqa: E402
from torchcontact.meshes import LinkMesh, load_meshes  # noqa: E402


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


if __name__ == "__main__":
    main()
