"""The ONNX runtime: single-frame latency, session options, batched throughput.

Graphs exported with ``torchcontact.export.export_estimator`` and run with
``torchcontact.runtime.EstimatorRuntime`` (onnxruntime, one thread):

1. ``EstimatorRuntime.step`` latency, one frame per call (10,000 calls after 500 warm-up calls,
   the configurations interleaved in rounds), with the graphs' node counts as exported and after
   onnxruntime's optimisation: the bundled arm with 2 force slots, and iCub ``l_arm_ft`` with 4
   slots and a correction stack (offset, inertial layer, the default MLP; random weights)
   chained into the graph; in the same process, one frame through the torch estimator as the
   reference;
2. the single-frame session options (threads, spinning, optimisation level, execution mode);
3. ``EstimatorRuntime.run`` throughput of the batched graph at 1e5 frames, beside the torch
   estimator (eager, and its generated C++ kernel) in the same process.

Run on a quiet machine: ``flock -x /tmp/tc-cpu.lock python benchmarks/runtime.py``
(``--calls 2000 --frames 20000`` for a quick look).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _meta import metadata  # noqa: E402
from robots import icub_path  # noqa: E402

import torchcontact as tc  # noqa: E402
from torchcontact.export import export_estimator, export_residual_checkpoint  # noqa: E402
from torchcontact.residual import (  # noqa: E402
    FeatureSpec,
    ResidualCorrection,
    ResidualMLP,
    subtree_bodies,
)
from torchcontact.runtime import EstimatorRuntime, session_options  # noqa: E402

TCARM = ("forearm_skin", "hand_skin"), ("force", "force")
ICUB = ("l_hand", "l_hand", "l_forearm", "l_forearm"), ("force", "force", "force", "wrench")


def _percentiles(ns: list[int]) -> tuple[float, float]:
    a = np.asarray(ns) / 1e3
    return float(np.percentile(a, 50)), float(np.percentile(a, 99))


def _frame(model: tc.RobotModel, K: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    nv = model.nv
    return dict(
        q=rng.uniform(-1, 1, nv),
        qd=rng.uniform(-1, 1, nv),
        qdd=rng.uniform(-1, 1, nv),
        ft=rng.normal(0, 10, (1, 6)),
        positions=rng.uniform(-0.03, 0.03, (K, 3)),
        active=np.ones(K),
    )


def _nodes(path: Path) -> tuple[int, int]:
    """Nodes as exported and after onnxruntime's optimisation (ORT_ENABLE_ALL)."""
    so = session_options()
    with tempfile.TemporaryDirectory() as d:
        so.optimized_model_filepath = f"{d}/opt.onnx"
        ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        return len(onnx.load(str(path)).graph.node), len(onnx.load(f"{d}/opt.onnx").graph.node)


def icub_correction(icub: tc.RobotModel, d: Path) -> Path:
    """A correction stack as training writes it, for iCub ``l_arm_ft``: offset, inertial layer
    on the sensor's subtree, the default MLP on the default features plus a temperature column
    (random weights); returns its checkpoint directory."""
    spec = FeatureSpec.default(icub, "l_arm_ft", extra=("temperature",))
    torch.manual_seed(0)
    mlp = ResidualMLP(len(spec.names(icub)))
    mlp.set_normalisation(torch.randn(64, len(spec.names(icub))), torch.randn(64, 6))
    bodies = tuple(icub.body_names[b] for b in subtree_bodies(icub, "l_arm_ft"))
    return ResidualCorrection(
        icub,
        "l_arm_ft",
        offset=torch.randn(6, dtype=torch.float64),
        inertial_bodies=bodies,
        delta=0.01 * torch.randn(10 * len(bodies), dtype=torch.float64),
        learned=mlp,
        features=spec,
    ).save(d / "residual")


def latency(calls: int, d: Path) -> None:
    """Section 1: single-frame latency of the step graph, interleaved configurations."""
    arm = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    icub = tc.RobotModel.from_urdf(icub_path())
    ckpt = icub_correction(icub, d)
    export_residual_checkpoint(ckpt, d / "residual.onnx", icub)
    configs = {}  # name -> (runtime, frame, extra, path)
    for dt in (torch.float32, torch.float64):
        tag = str(dt).removeprefix("torch.")
        p = d / f"tcarm-{tag}.onnx"
        export_estimator(arm, None, *TCARM, p, dtype=dt)
        configs[f"tcarm, 2 force slots, {tag}"] = (arm, p, {}, 2)
        p = d / f"icub-res-sensed-{tag}.onnx"
        export_estimator(
            icub, ["l_arm_ft"], *ICUB, p, dtype=dt, residual=d / "residual.onnx", joints="sensed"
        )
        configs[f"iCub l_arm_ft, 4 slots, residual, sensed joints, {tag}"] = (
            icub,
            p,
            {"temperature": 31.0},
            4,
        )
    p = d / "icub-res-all.onnx"
    export_estimator(
        icub, ["l_arm_ft"], *ICUB, p, dtype=torch.float32, residual=d / "residual.onnx"
    )
    configs["iCub l_arm_ft, 4 slots, residual, all 32 joints, float32"] = (
        icub,
        p,
        {"temperature": 31.0},
        4,
    )
    p = d / "icub-plain.onnx"
    export_estimator(icub, ["l_arm_ft"], *ICUB, p, dtype=torch.float32, joints="sensed")
    configs["iCub l_arm_ft, 4 slots, no residual, sensed joints, float32"] = (icub, p, {}, 4)
    runs = {}
    for name, (model, path, extra, K) in configs.items():
        rt = EstimatorRuntime(path, robot=model)
        f = _frame(model, K)
        kw = {"extra": extra} if extra else {}

        inputs = {**f, **kw}

        def step(rt=rt, inputs=inputs):
            return rt.step(inputs)

        out = step()
        assert out["status"] == 0, name
        raw = rt.backend.call  # the session's run on the packed input as it stands

        runs[name] = (step, raw, _nodes(path.with_name(path.name.replace(".onnx", ".step.onnx"))))
    times = {k: ([], []) for k in runs}
    rounds = 10
    for _ in range(rounds):  # interleaved: a noisy moment hurts every configuration alike
        for name, (step, raw, _) in runs.items():
            for _ in range(50):
                step()
            for _ in range(calls // rounds):
                t0 = time.perf_counter_ns()
                step()
                times[name][0].append(time.perf_counter_ns() - t0)
            for _ in range(calls // rounds):
                t0 = time.perf_counter_ns()
                raw()
                times[name][1].append(time.perf_counter_ns() - t0)
    # reference in the same process: one frame through the torch estimator (eager)
    ref = {}
    for label, model, sensors, (links, kinds) in (
        ("tcarm", arm, None, TCARM),
        ("iCub l_arm_ft", icub, ["l_arm_ft"], ICUB),
    ):
        est = tc.ContactEstimator(model, sensors, backend="eager")
        f = {k: torch.as_tensor(v)[None] for k, v in _frame(model, len(links)).items()}
        c = tc.Contacts(links, kinds, f["positions"])
        ft = {est.sensor_names[0]: f["ft"][:, 0]}
        for _ in range(20):
            est.estimate(f["q"], f["qd"], f["qdd"], ft, c)
        ns = []
        for _ in range(300):
            t0 = time.perf_counter_ns()
            est.estimate(f["q"], f["qd"], f["qdd"], ft, c)
            ns.append(time.perf_counter_ns() - t0)
        ref[label] = _percentiles(ns)
    print(f"\n1. single-frame latency, {calls:,} calls per configuration (µs)\n")
    print("| graph | nodes exported / optimised | step() p50 / p99 | session.run p50 / p99 |")
    print("|---|---|---|---|")
    for name, (_, _, nodes) in runs.items():
        s50, s99 = _percentiles(times[name][0])
        r50, r99 = _percentiles(times[name][1])
        print(
            f"| {name} | {nodes[0]} / {nodes[1]} | {s50:,.0f} / {s99:,.0f} |"
            f" {r50:,.0f} / {r99:,.0f} |"
        )
    for label, (p50, p99) in ref.items():
        print(
            f"| reference: torch estimator, eager, 1 frame, {label} | - |"
            f" {p50:,.0f} / {p99:,.0f} | - |"
        )


def session_choices(calls: int, d: Path) -> None:
    """Section 2: onnxruntime session options for one frame (the bundled arm, float32)."""
    arm = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    path = d / "opts.onnx"
    export_estimator(arm, None, *TCARM, path, dtype=torch.float32)
    step = path.with_name("opts.step.onnx")
    rt = EstimatorRuntime(path)
    f = _frame(arm, 2)
    rt.step(f)
    x = rt.backend.x[None].copy()

    def opts(**kw):
        so = session_options()
        for k, v in kw.items():
            if k.startswith("cfg:"):
                so.add_session_config_entry(k[4:], v)
            else:
                setattr(so, k, v)
        return so

    variants = {
        "chosen: 1 thread, sequential, no spinning, ORT_ENABLE_ALL": opts(),
        "2 intra-op threads, spinning": opts(
            intra_op_num_threads=2, **{"cfg:session.intra_op.allow_spinning": "1"}
        ),
        "2 intra-op threads, no spinning": opts(intra_op_num_threads=2),
        "parallel execution, 2 inter-op threads": opts(
            execution_mode=ort.ExecutionMode.ORT_PARALLEL, inter_op_num_threads=2
        ),
        "ORT_ENABLE_BASIC": opts(
            graph_optimization_level=ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
        ),
        "ORT_DISABLE_ALL": opts(
            graph_optimization_level=ort.GraphOptimizationLevel.ORT_DISABLE_ALL
        ),
        "no memory pattern": opts(enable_mem_pattern=False),
    }
    sess = {
        k: ort.InferenceSession(str(step), v, providers=["CPUExecutionProvider"])
        for k, v in variants.items()
    }
    times = {k: [] for k in sess}
    for _ in range(10):
        for k, s in sess.items():
            run, names = s._sess.run, [o.name for o in s.get_outputs()]
            ro, feed = ort.RunOptions(), {s.get_inputs()[0].name: x}
            for _ in range(50):
                run(names, feed, ro)
            for _ in range(calls // 10):
                t0 = time.perf_counter_ns()
                run(names, feed, ro)
                times[k].append(time.perf_counter_ns() - t0)
    print("\n2. single-frame session options, bundled arm float32 (session.run, µs)\n")
    print("| options | p50 / p99 |\n|---|---|")
    for k, v in times.items():
        p50, p99 = _percentiles(v)
        print(f"| {k} | {p50:,.0f} / {p99:,.0f} |")


def throughput(frames: int, d: Path) -> None:
    """Section 3: batched graph at ``frames`` frames vs the torch estimator."""
    arm = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    rng = np.random.default_rng(1)
    n = frames
    rows = []
    for dt in (torch.float32, torch.float64):
        tag = str(dt).removeprefix("torch.")
        path = d / f"batch-{tag}.onnx"
        export_estimator(arm, None, *TCARM, path, dtype=dt)
        rt = EstimatorRuntime(path)
        f = rt.dtype
        x = dict(
            q=rng.uniform(-1, 1, (n, 7)),
            qd=rng.uniform(-1, 1, (n, 7)),
            qdd=rng.uniform(-1, 1, (n, 7)),
            ft=rng.normal(0, 10, (n, 1, 6)),
            positions=rng.uniform(-0.05, 0.05, (n, 2, 3)),
            active=np.ones((n, 2)),
        )
        x = {k: v.astype(f) for k, v in x.items()}
        rt.run({k: v[:1000] for k, v in x.items()})
        best = []
        for _ in range(3):
            t0 = time.perf_counter()
            rt.run(x)
            best.append(time.perf_counter() - t0)
        nodes = len(onnx.load(str(path)).graph.node)
        rows.append((f"ONNX batched graph, {tag} ({nodes:,} nodes), 1 thread", n / min(best)))
        m = arm.to(dtype=dt)
        xt = {k: torch.from_numpy(v) for k, v in x.items()}
        c = tc.Contacts(*TCARM, xt["positions"], active=xt["active"] > 0)
        with torch.inference_mode():
            prev = torch.get_num_threads()
            torch.set_num_threads(1)
            for backend in ("eager", "cpu"):
                est = tc.ContactEstimator(m, backend=backend)
                est.estimate(
                    xt["q"][:4096],
                    xt["qd"][:4096],
                    xt["qdd"][:4096],
                    {"base_ft": xt["ft"][:4096, 0]},
                    tc.Contacts(*TCARM, xt["positions"][:4096]),
                )
                t0 = time.perf_counter()
                est.estimate(xt["q"], xt["qd"], xt["qdd"], {"base_ft": xt["ft"][:, 0]}, c)
                label = "eager torch" if backend == "eager" else "generated C++ kernel"
                rows.append(
                    (
                        f"reference: torch estimator, {label}, {tag}, 1 thread",
                        n / (time.perf_counter() - t0),
                    )
                )
            torch.set_num_threads(prev)
    print(f"\n3. batched throughput at {n:,} frames, bundled arm (frames/s)\n")
    print("| estimator | frames/s |\n|---|---|")
    for k, v in rows:
        print(f"| {k} | {v:,.0f} |")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--calls", type=int, default=10_000)
    p.add_argument("--frames", type=int, default=100_000)
    p.add_argument("--sections", default="1,2,3")
    args = p.parse_args()
    print(metadata() + f" | onnxruntime {ort.__version__}")
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        secs = args.sections.split(",")
        if "1" in secs:
            latency(args.calls, d)
        if "2" in secs:
            session_choices(args.calls, d)
        if "3" in secs:
            throughput(args.frames, d)


if __name__ == "__main__":
    main()
