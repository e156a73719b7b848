"""Contact localization on a CUDA device: the torch tree traversal against the CPU, and its rate.

Self-contained (torch, numpy and this repository only; no mesh files): a star-shaped mesh (a UV
sphere with random radii, concave in places) on the bundled arm's hand, pushes at random points of
it, readings from the estimator's forward model. Checks that ``Localizer`` on CUDA (``ray="torch"``)
gives the CPU brute-force result (status, link, point) in float64 and float32, then times
``Localizer.localize`` end to end and the ray casting alone at ``--batch`` frames.

Run: ``python benchmarks/localize_gpu.py [--batch 100000] [--faces 1500]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import torchcontact as tc  # noqa: E402
from torchcontact.localize import Localizer, cast_bvh  # noqa: E402
from torchcontact.meshes import LinkMesh  # noqa: E402


def star_mesh(rng, rings, segments, scale=0.06):
    th = np.linspace(0, np.pi, rings + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    v = [[0, 0, 1.0]] + [[np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)] for t in th
                         for p in ph] + [[0, 0, -1.0]]  # fmt: skip
    v = np.array(v) * scale * rng.uniform(0.7, 1.3, (len(v), 1))
    f = [[0, 1 + j, 1 + (j + 1) % segments] for j in range(segments)]
    for i in range(rings - 2):
        for j in range(segments):
            a, b = 1 + i * segments + j, 1 + i * segments + (j + 1) % segments
            f += [[a, a + segments, b], [b, a + segments, b + segments]]
    last = len(v) - 1
    base = 1 + (rings - 2) * segments
    f += [[base + j, last, base + (j + 1) % segments] for j in range(segments)]
    return v, np.array(f)


def frames(model, mesh, n, rng, dev, dtype):
    tri = mesh.vertices[mesh.faces]
    k = rng.integers(len(tri), size=n)
    p = np.einsum("nk,nki->ni", rng.dirichlet([1, 1, 1], size=n), tri[k])
    nrm = np.cross(tri[k, 1] - tri[k, 0], tri[k, 2] - tri[k, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    f = -(nrm + 0.3 * rng.normal(size=(n, 3))) * 5
    m = model.to(dev, torch.float64)
    q = torch.as_tensor(rng.uniform(-1, 1, (n, model.nv)), device=dev)
    est = tc.ContactEstimator(m, backend="eager")
    w = torch.as_tensor(np.c_[f, np.zeros((n, 3))], device=dev)[:, None]
    c = tc.Contacts(["hand"], ["known"], torch.as_tensor(p, device=dev)[:, None], wrenches=w)
    ft = est.predict_ft(q, q * 0.1, q * 0.1, c)
    return q.to(dtype), {k: v.to(dtype) for k, v in ft.items()}, p


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, default=100_000)
    ap.add_argument("--faces", type=int, default=1500)
    args = ap.parse_args()
    print("torch", torch.__version__, "cuda", torch.cuda.is_available(),
          torch.cuda.get_device_name() if torch.cuda.is_available() else "")  # fmt: skip
    if not torch.cuda.is_available():
        return
    rng = np.random.default_rng(0)
    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    segments = max(8, int(np.sqrt(args.faces / 2)))
    v, f = star_mesh(rng, segments, segments)
    fr = model.frame("hand")
    mesh = LinkMesh("hand", fr.body, v, f, fr.R_body_frame, fr.p_body_frame, None, ("star",))
    print(f"mesh: {len(f)} triangles")
    for dtype in (torch.float64, torch.float32):
        md = model.to("cuda", dtype)
        q, ft, p = frames(model, mesh, 2000, rng, "cuda", dtype)
        gpu = Localizer(md, {"hand": mesh}, links=["hand"], ray="torch", backend="eager")
        r = gpu.localize(q, q * 0.1, q * 0.1, ft)["base_ft"]
        cpu = Localizer(model.to(dtype=dtype), {"hand": mesh}, links=["hand"], ray="brute",
                        backend="eager")  # fmt: skip
        rc = cpu.localize(q.cpu(), q.cpu() * 0.1, q.cpu() * 0.1,
                          {k: x.cpu() for k, x in ft.items()})["base_ft"]  # fmt: skip
        same = (r.status.cpu() == rc.status).float().mean().item()
        ok = (r.status.cpu() == 0) & (rc.status == 0)
        err = (r.position.cpu()[ok] - rc.position[ok]).abs().max().item()
        truth = (r.position.cpu()[ok].double() - torch.as_tensor(p)[ok]).norm(dim=-1)
        print(f"{dtype}: CUDA vs CPU brute force: same status {100 * same:.2f} %, max |point"
              f" diff| {err:.1e} m; CUDA point vs truth (unambiguous) median"
              f" {truth.median().item():.1e} m")  # fmt: skip
        # throughput at the batch
        q, ft, _ = frames(model, mesh, args.batch, rng, "cuda", dtype)
        qd = q * 0.1
        for _ in range(2):
            gpu.localize(q, qd, qd, ft)
        torch.cuda.synchronize()
        ts = []
        for _ in range(5):
            t0 = time.perf_counter()
            gpu.localize(q, qd, qd, ft)
            torch.cuda.synchronize()
            ts.append(time.perf_counter() - t0)
        t = float(np.median(ts))
        # the casting alone
        n = args.batch
        orig = torch.randn(n, 3, device="cuda", dtype=dtype) * 0.05
        dirs = torch.nn.functional.normalize(torch.randn(n, 3, device="cuda", dtype=dtype), dim=-1)
        tsd = gpu.triangles
        cast_bvh(tsd, orig, dirs, torch.zeros(n, dtype=torch.int64, device="cuda"))
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(5):
            cast_bvh(tsd, orig, dirs, torch.zeros(n, dtype=torch.int64, device="cuda"))
        torch.cuda.synchronize()
        tcast = (time.perf_counter() - t0) / 5
        print(
            f"{dtype}: localize end to end (eager line program) {n / t:,.0f} frames/s;"
            f" ray casting alone {n / tcast:,.0f} lines/s"
        )


if __name__ == "__main__":
    main()
