"""Single-frame latency of the step graph and runtime: this tree against an earlier commit.

The deployment wing moved into ``torchcontact/onnx/`` (issue 21), the online wing was wired
into it (issue 23: the C backend, the online stage); the latency of a step without the online
options must not get worse. This script exports the same graphs with both versions (the
earlier one from a ``git archive`` of ``--against``, in a subprocess) and times, in this one
process, the earlier ``EstimatorRuntime.step`` (its package imported beside this tree,
``_meta.load_old_package``) on its graphs against this tree's on its own, the configurations
and the two versions interleaved in rounds (a noisy moment hurts both alike). Reported: p50 and
p99 of ``step()`` and of the bare ``session.run`` per version, and the ratios new / old; the
last configuration (a learned correction) is issue 23's ONNX-step goal (p99 <= 0.7x today's).
Step nodes: those a full-rank frame runs (the main graph's and the ``If`` branches it takes, the
solve's sweep; every slot is active here), as written and after onnxruntime's optimisation (what
runs). Latency follows the second count, not exactly: an ``If`` costs about ten plain nodes,
onnxruntime's ``Det`` and large ``Gather`` index sets more than one.
The cost of the online options is the extra row: this tree's graph exported ``online``, bias
tracked.

Run on a quiet machine: ``flock -x /tmp/tc-cpu.lock python benchmarks/runtime_refactor.py``
(``--calls 2000`` for a quick look).
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))
from _meta import load_old_package, metadata  # noqa: E402
from robots import icub_path  # noqa: E402
from runtime import icub_correction  # noqa: E402 - benchmarks/runtime.py

import torchcontact as tc  # noqa: E402
from torchcontact.export import export_estimator, export_residual_checkpoint  # noqa: E402
from torchcontact.runtime import EstimatorRuntime  # noqa: E402

TCARM = (("forearm_skin", "hand_skin"), ("force", "force"))
ICUB = (("l_hand", "l_hand", "l_forearm", "l_forearm"), ("force", "force", "force", "wrench"))

#: name -> (robot, sensors, layout, dtype, residual?, joints)
CONFIGS = {
    "tcarm, 2 force slots, float32": ("tcarm", None, TCARM, "float32", False, None),
    "tcarm, 2 force slots, float64": ("tcarm", None, TCARM, "float64", False, None),
    "iCub l_arm_ft, 4 slots, sensed joints, float32": (
        "icub", ["l_arm_ft"], ICUB, "float32", False, "sensed"),
    "iCub l_arm_ft, 4 slots, residual stack, sensed joints, float32": (
        "icub", ["l_arm_ft"], ICUB, "float32", True, "sensed"),
}  # fmt: skip

_EXPORT = """
import json, sys, torch
import torchcontact as tc
from torchcontact.export import export_estimator, export_residual_checkpoint
configs, out, icub, ckpt = json.loads(sys.argv[1])
models = {"tcarm": tc.RobotModel.from_urdf(tc.robots.tcarm_path()),
          "icub": tc.RobotModel.from_urdf(icub)}
if ckpt:
    export_residual_checkpoint(ckpt, out + "/old-residual.onnx", models["icub"], check=False)
for i, (robot, sensors, (links, kinds), dt, res, joints) in enumerate(configs):
    export_estimator(models[robot], sensors, links, kinds, f"{out}/old-{i}.onnx",
                     dtype=getattr(torch, dt), joints=joints,
                     residual=out + "/old-residual.onnx" if res else None)
"""


def _frame(nv: int, K: int, extra: bool, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    f = dict(q=rng.uniform(-1, 1, nv), qd=rng.uniform(-1, 1, nv), qdd=rng.uniform(-1, 1, nv),
             ft=rng.normal(0, 10, (1, 6)), positions=rng.uniform(-0.03, 0.03, (K, 3)),
             active=np.ones(K))  # fmt: skip
    if extra:
        f["extra"] = {"temperature": 31.0}
    return f


def step_nodes(path: Path) -> int:
    """Nodes a full-rank frame runs in a step graph: the main graph's, plus each ``If``'s
    ``then_branch`` (the solve's sweep and its full-rank result), recursively."""

    def count(graph) -> int:
        n = 0
        for node in graph.node:
            n += 1
            for a in node.attribute:
                if node.op_type == "If" and a.name == "then_branch":
                    n += count(a.g)
        return n

    return count(onnx.load(str(path)).graph)


def optimized_nodes(path: Path) -> int:
    """:func:`step_nodes` of the graph onnxruntime runs: after its optimisation (the runtime's
    level, ``ORT_ENABLE_ALL``: identities, casts to the same type and repeated subexpressions
    removed, ``x * sigmoid(x)`` fused)."""
    out = path.with_name(path.stem + ".opt.onnx")
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.optimized_model_filepath = str(out)
    so.log_severity_level = 3
    ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    return step_nodes(out)


def _raw(rt):
    """The bare single-frame graph call of a runtime of either version."""
    backend = getattr(rt, "backend", None)
    if backend is not None and hasattr(backend, "call"):
        return backend.call
    run, names, x, ro, xin = (rt.step_session._sess.run, rt._out_names, rt._x, ort.RunOptions(),
                              rt._in_name)  # fmt: skip
    return lambda: run(names, {xin: x}, ro)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", default="ba76886", help="the earlier commit (default ba76886)")
    ap.add_argument("--calls", type=int, default=10000, help="timed calls per configuration")
    args = ap.parse_args()
    print(metadata())
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        tree = d / "old"
        tree.mkdir()
        arch = subprocess.run(["git", "-C", str(ROOT), "archive", args.against],
                              capture_output=True, check=True).stdout  # fmt: skip
        (d / "old.tar").write_bytes(arch)
        with tarfile.open(d / "old.tar") as t:
            t.extractall(tree, filter="data")
        ckpt = icub_correction(tc.RobotModel.from_urdf(icub_path()), d)
        configs = list(CONFIGS.values())
        job = [configs, str(d), str(icub_path()), str(ckpt)]
        env = {"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"}
        import json
        import os

        subprocess.run([sys.executable, "-c", _EXPORT, json.dumps(job)], check=True,
                       env={**os.environ, **env}, cwd=tree)  # fmt: skip
        old = importlib.import_module(f"{load_old_package(args.against, d).__name__}.runtime")
        models = {"tcarm": tc.RobotModel.from_urdf(tc.robots.tcarm_path()),
                  "icub": tc.RobotModel.from_urdf(icub_path())}  # fmt: skip
        export_residual_checkpoint(ckpt, d / "new-residual.onnx", models["icub"], check=False)
        runs = {}
        for i, (name, (robot, sensors, (links, kinds), dt, res, joints)) in enumerate(
            CONFIGS.items()
        ):
            path = d / f"new-{i}.onnx"
            export_estimator(models[robot], sensors, links, kinds, path,
                             dtype=getattr(torch, dt), joints=joints,
                             residual=d / "new-residual.onnx" if res else None)  # fmt: skip
            f = _frame(models[robot].nv, len(links), res)
            rt_old = old.EstimatorRuntime(d / f"old-{i}.onnx")
            rt_new = EstimatorRuntime(path)
            legacy = (f["q"], f["qd"], f["qdd"], f["ft"], f["positions"], f["active"])
            kw = {"extra": f["extra"]} if res else {}
            a, b = rt_old.step(*legacy, **kw), rt_new.step(f)
            np.testing.assert_allclose(a["force"], b["force"], rtol=1e-4, atol=1e-4)

            steps = [p.with_name(p.name.replace(".onnx", ".step.onnx"))
                     for p in (d / f"old-{i}.onnx", path)]  # fmt: skip
            nodes = [step_nodes(p) for p in steps] + [optimized_nodes(p) for p in steps]
            runs[name] = {
                "old step": lambda rt=rt_old, a=legacy, kw=kw: rt.step(*a, **kw),
                "new step": lambda rt=rt_new, f=f: rt.step(f),
                "old run": _raw(rt_old),
                "new run": _raw(rt_new),
                "nodes": nodes,
            }
        # the online options' cost: the last configuration exported online, the bias tracked
        robot, sensors, (links, kinds), dt, res, joints = list(CONFIGS.values())[-1]
        path = d / "new-online.onnx"
        export_estimator(models[robot], sensors, links, kinds, path, dtype=getattr(torch, dt),
                         joints=joints, residual=d / "new-residual.onnx" if res else None,
                         online=True)  # fmt: skip
        rt_on = EstimatorRuntime(path, track_bias=True)
        f = _frame(models[robot].nv, len(links), res)
        f["active"] = np.zeros(len(links))  # contact-free: the tracker updates every frame
        rt_on.step(f)
        n_on = step_nodes(path.with_name("new-online.step.onnx"))
        runs[list(CONFIGS)[-1]].update(
            {
                "online step": lambda rt=rt_on, f=f: rt.step(f),
                "online run": _raw(rt_on),
                "online nodes": n_on,
            }
        )
        times = {n: {k: [] for k in fns if "nodes" not in k} for n, fns in runs.items()}
        rounds = 20
        for _ in range(rounds):  # interleaved: configurations and versions alike
            for name, fns in runs.items():
                for k in times[name]:
                    fn = fns[k]
                    for _ in range(20):
                        fn()
                    for _ in range(args.calls // rounds):
                        t0 = time.perf_counter_ns()
                        fn()
                        times[name][k].append(time.perf_counter_ns() - t0)
    print(f"\nsingle-frame latency against {args.against}, {args.calls:,} calls each (µs)\n")
    print("| graph | step nodes old / new (optimised) | step() p50 old / new (ratio) |"
          " p99 old / new (ratio) | session.run p50 old / new (ratio) |")  # fmt: skip
    print("|---|---|---|---|---|")
    for name, t in times.items():
        p = {k: np.percentile(np.asarray(v) / 1e3, [50, 99]) for k, v in t.items()}
        so, sn, ro, rn = p["old step"], p["new step"], p["old run"], p["new run"]
        n_old, n_new, o_old, o_new = runs[name]["nodes"]
        step = f"{so[0]:.0f} / {sn[0]:.0f} ({sn[0] / so[0]:.2f})"
        run = f"{ro[0]:.0f} / {rn[0]:.0f} ({rn[0] / ro[0]:.2f})"
        p99 = f"{so[1]:.0f} / {sn[1]:.0f} ({sn[1] / so[1]:.2f})"
        print(f"| {name} | {n_old} / {n_new} ({o_old} / {o_new}) | {step} | {p99} | {run} |")
        if "online step" in p:
            on, rn_on = p["online step"], p["online run"]
            print(f"| {name}, online, bias tracked (this tree) | - / {runs[name]['online nodes']}"
                  f" | - / {on[0]:.0f} ({on[0] / so[0]:.2f}) | - / {on[1]:.0f} |"
                  f" - / {rn_on[0]:.0f} ({rn_on[0] / ro[0]:.2f}) |")  # fmt: skip


if __name__ == "__main__":
    main()
