"""On the robot, online: C step latency, bias step, payload identification, a new session.

1. **Latency** (iCub ``l_arm_ft``, 4 slots: two forces on ``l_hand``, a force and a wrench on
   ``l_forearm``; a correction stack with offset and inertial layers; float64; the joints the
   sensor determines), one frame per call, configurations interleaved in rounds, in one process:

   - the C step (``export_c_step``): the library call alone (ctypes), and
     ``EstimatorRuntime(path, backend="c").step`` (inputs, call, outputs, bias tracking, in
     Python), beside round 1's ``CStepRuntime.step`` (the package of ``--before``, imported
     beside this tree) on the same library: the wrapper's overhead, old against new;
   - the C step from C (``examples/c_step.c --bench``, a separate process, same machine);
   - the ONNX step (``EstimatorRuntime.step``, one onnxruntime thread) with the same
     correction stack chained inside (offset + inertial), with an MLP layer on top (the step
     with a learned correction), and the latter exported ``online`` (bias and payload inputs,
     ``ft_model`` and the regressor outputs) with the bias tracked;
   - iDynTree's per-frame estimate (``updateKinematicsFromFixedBase`` +
     ``estimateExtWrenchesAndJointTorques``, whole iCub, its six F/T sensors, a full-wrench
     unknown at ``root_link``, a pure force on ``l_hand`` and one on ``l_forearm``: iDynTree
     returns NaN for the four slots' 15 unknowns on one sensor, which the C step solves by
     minimum norm, so it gets the 6-unknown case of ``benchmarks/estimator.py``).

   Today's ONNX step against this tree's (graph and runtime, both versions in one process):
   ``benchmarks/runtime_refactor.py --against <commit>``.

2. **Streams** (simulated at 100 Hz, ``tests/online_scenes.py``; the C runtime): a 2 N offset step
   (contact-free seconds until the contact-force error is back below 0.3 N), and a 0.5 kg payload
   added mid-stream (seconds of motion until ``identify_payload()`` answers, and its mass error),
   on the bundled arm and on iCub ``l_arm_ft``.

3. **New session** (benchmarks/README.md's ``train heldout --new-session`` drift + cable case: iCub
   ``l_arm_ft``, noise x2.6, a stack trained on 36,000 frames of one session, scored on 12,000
   frames of another): contact-force RMSE on one-contact frames with the chosen stack alone (the
   benchmarks/README.md's 2.362 N), and with the bias tracked from the model over the test log
   (``track_log``: the causal filter, and the forward-backward smoother) on top of the constant
   offset and of the chosen stack.

Every figure is printed with the CPU model (``lscpu``); the machine may be shared, so compare
within one run. ``python benchmarks/online.py [--sections latency streams session]
[--calls 20000] [--before ba76886]``.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))
from _meta import load_old_package, metadata  # noqa: E402
from online_scenes import (  # noqa: E402
    NOISE,
    bias_step_stream,
    payload_stream,
    recovery,
    run_stream,
)
from robots import icub_path, load_model  # noqa: E402

import torchcontact as tc  # noqa: E402
from torchcontact.online.cstep import export_c_step  # noqa: E402
from torchcontact.online.payload import NotIdentifiableError  # noqa: E402
from torchcontact.residual import ResidualCorrection, subtree_bodies  # noqa: E402
from torchcontact.runtime import EstimatorRuntime  # noqa: E402

ICUB = ("l_hand", "l_hand", "l_forearm", "l_forearm"), ("force", "force", "force", "wrench")


def cpu_model() -> str:
    """The CPU model as ``lscpu`` names it."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            if line.startswith("Model name"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return "unknown CPU"


def _pct(ns: list[int]) -> tuple[float, float]:
    a = np.asarray(ns) / 1e3
    return float(np.percentile(a, 50)), float(np.percentile(a, 99))


def _stack(model: tc.RobotModel, d: Path, mlp: bool) -> Path:
    """A correction stack as training writes it: offset, inertial layer (random), MLP."""
    from torchcontact.residual import FeatureSpec, ResidualMLP

    bodies = tuple(model.body_names[b] for b in subtree_bodies(model, "l_arm_ft"))
    g = torch.Generator().manual_seed(0)
    kw = {}
    if mlp:
        spec = FeatureSpec.default(model, "l_arm_ft")
        net = ResidualMLP(len(spec.names(model)))
        net.set_normalisation(torch.randn(64, len(spec.names(model))), torch.randn(64, 6))
        kw = dict(learned=net, features=spec)
    return ResidualCorrection(
        model, "l_arm_ft", offset=torch.randn(6, dtype=torch.float64, generator=g),
        inertial_bodies=bodies,
        delta=0.01 * torch.randn(10 * len(bodies), dtype=torch.float64, generator=g), **kw,
    ).save(d / ("stack-mlp" if mlp else "stack"))  # fmt: skip


def _idyntree(model: tc.RobotModel, frame: dict) -> callable:
    """One frame of iDynTree's estimator (whole iCub, its six sensors), as a callable."""
    import idyntree.swig as idt

    e = idt.ExtWrenchesAndJointTorquesEstimator()
    assert e.loadModelAndSensorsFromFileWithSpecifiedDOFs(str(icub_path()), list(model.joint_names))
    m, sens = e.model(), e.sensors()
    root = m.getFrameIndex("root_link")
    grav = idt.Vector3.FromPython([0.0, 0.0, -9.81])
    meas = idt.SensorsMeasurements(sens)
    cw, tau = idt.LinkContactWrenches(m), idt.JointDOFsDoubleArray(m)
    u = idt.LinkUnknownWrenchContacts(m)
    T = idt.SIX_AXIS_FORCE_TORQUE
    j = sens.getSensorIndex(T, "l_arm_ft")
    others = [k for k in range(sens.getNrOfSensors(T)) if k != j]
    zero = idt.Wrench.FromPython(np.zeros(6))
    links = [m.getLinkIndex(k) for k in ("l_hand", "l_forearm")]
    kinds = [idt.PURE_FORCE, idt.PURE_FORCE]
    q = idt.JointPosDoubleArray.FromPython(frame["q"])
    qd = idt.JointDOFsDoubleArray.FromPython(frame["qd"])
    qdd = idt.JointDOFsDoubleArray.FromPython(frame["qdd"])
    w = idt.Wrench.FromPython(frame["ft"][0])
    pos = [idt.Position.FromPython(p) for p in frame["positions"][1:3]]

    def step() -> None:
        e.updateKinematicsFromFixedBase(q, qd, qdd, root, grav)
        u.clear()
        u.addNewUnknownFullWrenchInFrameOrigin(m, root)
        for li, kd, p in zip(links, kinds, pos, strict=True):
            u.addNewContactForLink(li, idt.UnknownWrenchContact(kd, p))
        meas.setMeasurement(T, j, w)
        for k in others:  # the other five sensors read zero (their submodels are contact-free)
            meas.setMeasurement(T, k, zero)
        if not e.estimateExtWrenchesAndJointTorques(u, meas, cw, tau):
            raise RuntimeError("iDynTree's estimate failed")

    return step


def latency(calls: int, d: Path, before: str | None) -> None:
    """Section 1: single-frame latency, every path in this process."""
    from torchcontact.export import export_estimator, export_residual_checkpoint

    model = load_model("icub")
    rng = np.random.default_rng(0)
    frame = dict(q=rng.uniform(-1, 1, model.nv), qd=rng.uniform(-1, 1, model.nv),
                 qdd=rng.uniform(-1, 1, model.nv), ft=rng.normal(0, 10, (1, 6)),
                 positions=rng.uniform(-0.03, 0.03, (4, 3)), active=np.zeros(4))  # fmt: skip
    stack, stack_mlp = _stack(model, d, False), _stack(model, d, True)
    t0 = time.perf_counter()
    lib = d / "icub.so"
    export_c_step(model, ["l_arm_ft"], *ICUB, lib, correction=stack, joints="sensed")
    build_s = time.perf_counter() - t0
    c = EstimatorRuntime(lib, robot=model, track_bias=True)
    assert c.step(frame)["status"] == 0
    runs = {
        "C step: the library call (ctypes)": c.backend.call_raw,
        'C step: EstimatorRuntime(backend="c").step (Python I/O, bias tracking)':
            lambda: c.step(frame),
    }  # fmt: skip
    if before:  # round 1's wrapper on the same library
        import importlib

        old = load_old_package(before, d)
        oc = importlib.import_module(f"{old.__name__}.online.cruntime").CStepRuntime(
            lib, track_bias=True
        )
        args = [frame[k] for k in ("q", "qd", "qdd", "ft", "positions", "active")]
        np.testing.assert_allclose(oc.step(*args)["force"], c.step(frame)["force"], atol=1e-12)
        runs[f"C step: CStepRuntime.step of {before} (round 1)"] = lambda: oc.step(*args)
    for name, ck, online in (
        ("offset + inertial", stack, False),
        ("offset + inertial + MLP", stack_mlp, False),
        ("offset + inertial + MLP, online, bias tracked", stack_mlp, True),
    ):
        res = d / f"{ck.name}.onnx"
        export_residual_checkpoint(ck, res, model, check=False)
        p = d / f"icub-{ck.name}{'-online' if online else ''}.onnx"
        export_estimator(model, ["l_arm_ft"], *ICUB, p, dtype=torch.float64, residual=res,
                         joints="sensed", online=online)  # fmt: skip
        rt = EstimatorRuntime(p, robot=model, track_bias=online)
        assert rt.step(frame)["status"] == 0
        runs[f"ONNX step, {name}"] = lambda rt=rt: rt.step(frame)
    runs["iDynTree per-frame estimate (whole iCub)"] = _idyntree(model, frame)
    times: dict[str, list[int]] = {k: [] for k in runs}
    rounds = 10
    for _ in range(rounds):  # interleaved: a noisy moment hurts every path alike
        for name, fn in runs.items():
            for _ in range(50):
                fn()
            for _ in range(calls // rounds):
                t = time.perf_counter_ns()
                fn()
                times[name].append(time.perf_counter_ns() - t)
    cpu = cpu_model()
    ref = _pct(times["iDynTree per-frame estimate (whole iCub)"])
    print(f"\n1. single-frame latency, iCub l_arm_ft, 4 slots, offset + inertial correction,"
          f" float64; {calls:,} calls per path; CPU: {cpu}\n")  # fmt: skip
    print("| path | p50 / p99 µs | p50 / p99 vs iDynTree | CPU |")
    print("|---|---|---|---|")
    for name in runs:
        p50, p99 = _pct(times[name])
        print(f"| {name} | {p50:,.1f} / {p99:,.1f} | {p50 / ref[0]:.3f} / {p99 / ref[1]:.3f} |"
              f" {cpu} |")  # fmt: skip
    raw = _pct(times["C step: the library call (ctypes)"])[0]
    new = _pct(times[list(runs)[1]])[0] - raw
    line = f"\nPython around the C call (p50): {new:,.1f} µs"
    if before:
        old = _pct(times[f"C step: CStepRuntime.step of {before} (round 1)"])[0] - raw
        line += f"; round 1's: {old:,.1f} µs (new / old {new / old:.2f})"
    print(line + f"; CPU: {cpu}")
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc:
        exe = d / "c_step"
        subprocess.run([cc, "-O2", "-include", str(lib.with_suffix(".h")),
                        str(ROOT / "examples" / "c_step.c"), str(lib), f"-Wl,-rpath,{d}", "-lm",
                        "-o", str(exe)], check=True)  # fmt: skip
        x = " ".join(repr(float(v)) for v in c.backend.x)
        r = subprocess.run([str(exe), "--bench", str(calls * 5)], input=x, capture_output=True,
                           text=True, check=True).stdout.split()  # fmt: skip
        print(f"| C step from C (examples/c_step.c, own process) | {int(r[1]) / 1e3:,.1f} /"
              f" {int(r[3]) / 1e3:,.1f} | - | {cpu} |")  # fmt: skip
    print(
        f"\nC library: {lib.stat().st_size // 1024} KiB, export + build {build_s:.1f} s"
        " (cached builds are copied)"
    )


def _first_answer(rt: EstimatorRuntime, s, k0: int, truth: float) -> tuple[float, float]:
    """Seconds of motion until identify_payload() answers, and the answer's relative error."""
    rt.start_identification()
    for i in range(k0, len(s.t)):
        rt.step(s.q[i], s.qd[i], s.qdd[i], s.ft[i], s.positions[i], s.active[i], t=s.t[i])
        if (i - k0) % 10 == 9:
            try:
                p = rt.identify_payload(apply=False)
            except NotIdentifiableError:
                continue
            return float(s.t[i] - s.t[k0]), abs(p.mass - truth) / truth
    return float("inf"), float("nan")


def streams(d: Path) -> None:
    """Section 2: the offset step and the payload on simulated streams (C runtime)."""
    cpu = cpu_model()
    print(f"\n2. simulated streams at 100 Hz, C runtime (time constant 0.5 s); CPU: {cpu}\n")
    print("| robot, sensor | offset step: contact-free s until the offset error < 0.3 N |"
          " contact frames: last >= 0.3 N / first of the rest (contact-free s) |"
          " payload 0.5 kg: s of motion to an answer | its mass error |")  # fmt: skip
    print("|---|---|---|---|---|")
    for robot, sensor in (("tcarm", "base_ft"), ("icub", "l_arm_ft")):
        model = (tc.RobotModel.from_urdf(tc.robots.tcarm_path()) if robot == "tcarm"
                 else load_model("icub"))  # fmt: skip
        step = bias_step_stream(model, seconds=30.0, step_s=10.0, sensor=sensor)
        lib = d / f"{robot}-stream.so"
        export_c_step(model, [sensor], step.links, step.kinds, lib, joints="sensed")
        rt = EstimatorRuntime(lib, robot=model, track_bias=True,
                              tracker_options=dict(ft_std=NOISE))  # fmt: skip
        k0 = int(np.searchsorted(step.t, 10.0))
        run_stream(rt, step, 0, k0)
        rec = recovery(step, run_stream(rt, step, k0), k0)
        pay = payload_stream(model, mass=0.5, seconds=30.0, change_s=5.0, sensor=sensor)
        rt = EstimatorRuntime(lib, robot=model, track_bias=True,
                              tracker_options=dict(ft_std=NOISE))  # fmt: skip
        k1 = int(np.searchsorted(pay.t, 5.0))
        run_stream(rt, pay, 0, k1)
        secs, err = _first_answer(rt, pay, k1, 0.5)
        print(f"| {robot}, {sensor} | {rec['offset_s']:.2f} | {rec['last_bad_s']:.2f} /"
              f" {rec['contact_s']:.2f} | {secs:.2f} | {100 * err:.2f} % |")  # fmt: skip


def new_session(epochs: int, bias_tau: float = 0.0) -> None:
    """Section 3: benchmarks/README.md's --new-session drift + cable case, with the bias tracked."""
    from dataclasses import replace

    from torchcontact.online.estimator import OnlineEstimator, track_log
    from torchcontact.simulation import UnmodeledEffects, simulate
    from training.__main__ import CONDITIONS
    from training.data import ResidualDataset
    from training.evaluate import contact_metrics
    from training.fit import TrainConfig
    from training.pipeline import Config, DataConfig, make_dataset, predict, train

    model, sensor = load_model("icub"), "l_arm_ft"
    fx = dict(CONDITIONS["drift+cable"])
    fx["noise_std"] = tuple(2.6 * x for x in fx["noise_std"])
    torch.manual_seed(0)
    cfg = Config(data=DataConfig(robot="icub", sensor=sensor, force_max=10.0),
                 train=TrainConfig(kind="mlp", seed=0, epochs=epochs))  # fmt: skip
    data = replace(cfg.data, frames=36000, seed=0, effects=dict(fx), folds=0)
    cfg = replace(cfg, data=data)
    t0 = time.perf_counter()
    trained = train(model, make_dataset(model, data, sensor), cfg)
    train_s = time.perf_counter() - t0
    log = simulate(model, 12000, sensor=sensor, seed=1000, rate_hz=data.rate_hz,
                   force_max=data.force_max, effects=UnmodeledEffects(**fx))  # fmt: skip
    test = ResidualDataset.from_simulated(log, data.extra)
    span = [(0, len(test))]
    free = test.contact_free
    t = test.t_ns * 1e-9
    preds = {"none": np.zeros((len(test), 6))}
    preds["chosen stack alone (README: 2.362)"] = predict(
        trained.final.corrections[trained.final.chosen], test, span)  # fmt: skip
    chosen = trained.final.corrections[trained.final.chosen]
    stacks = [("constant offset", trained.final.corrections["offset"]),
              (f"chosen stack ({trained.final.chosen})", chosen)]  # fmt: skip
    if bias_tau > 0:  # train fit --bias-time-constant: the session's drift out of the targets
        smooth_cfg = replace(cfg, data=replace(data, bias_time_constant=bias_tau))
        torch.manual_seed(0)
        st = train(model, make_dataset(model, data, sensor), smooth_cfg)
        sc = st.final.corrections[st.final.chosen]
        preds[f"stack fitted with bias smoothing {bias_tau:g} s ({st.final.chosen}) alone"] = (
            predict(sc, test, span)
        )
        stacks.append((f"stack fitted with bias smoothing {bias_tau:g} s ({st.final.chosen})", sc))
    for label, corr in stacks:
        online = OnlineEstimator(model, [sensor], correction=corr, backend="cpu",
                                 tracker_options=dict(ft_std=fx["noise_std"]))  # fmt: skip
        extra = {c: test.extra[c] for c in corr.extra_columns}
        for smooth in (False, True):
            tr = track_log(online, test.q, test.qd, test.qdd, test.ft, free, t, extra=extra,
                           smoother=smooth, time_constant=0.5, ft_std=fx["noise_std"])  # fmt: skip
            name = f"{label} + bias tracked, {'smoother' if smooth else 'causal filter'}"
            preds[name] = test.ft - tr.ft[:, 0]
    est = tc.ContactEstimator(model, [sensor])
    contact = np.flatnonzero(~free & test.usable)
    truth = {k: v[contact] for k, v in test.truth.items() if k != "links"}
    truth["links"] = test.truth["links"]
    cpu = cpu_model()
    print(f"\n3. new session, drift + cable, iCub l_arm_ft, noise x2.6, stack trained in"
          f" {train_s:.0f} s ({epochs} epochs); contact-force RMSE on one-contact frames of the"
          f" other session (goal <= 0.5 N); CPU: {cpu}\n")  # fmt: skip
    print("| correction | force RMSE 1c (N) | 2c (N) |\n|---|---|---|")
    for name, p in preds.items():
        m = contact_metrics(est, test.q[contact], test.qd[contact], test.qdd[contact],
                            test.ft[contact] - p[contact], truth, sensor)  # fmt: skip
        print(f"| {name} | {m['force_rmse']:.3f} | {m.get('force_rmse_2c', float('nan')):.3f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sections", nargs="+", default=["latency", "streams", "session"],
                    choices=["latency", "streams", "session"])  # fmt: skip
    ap.add_argument("--calls", type=int, default=20000)
    ap.add_argument("--epochs", type=int, default=150, help="learned layer (section 3)")
    ap.add_argument(
        "--bias-smoothing",
        type=float,
        default=120.0,
        help="section 3: also a stack fitted with train fit --bias-time-constant S (0: skip)",
    )
    ap.add_argument(
        "--before",
        default="ba76886",
        help="round 1's commit, for its CStepRuntime beside this tree (empty: skip)",
    )
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(metadata())
    print(f"lscpu model name: {cpu_model()}")
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        if "latency" in args.sections:
            latency(args.calls, d, args.before or None)
        if "streams" in args.sections:
            streams(d)
        if "session" in args.sections:
            new_session(args.epochs, args.bias_smoothing)


if __name__ == "__main__":
    main()
