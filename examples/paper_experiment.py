"""Reproduce the statistical analysis of Del Prete et al. (HRI 2012), Sec. 3, on the iCub.

Two pure-force contacts on the left forearm, behind the left arm F/T sensor: 6 unknowns, rank 5.
Forces have norms uniform in [0, K] and directions uniform on the sphere; the readings are the
model's exact prediction. The minimum-norm solution misses the one unobservable direction (equal
and opposite forces along the line through the two contact points), so each force's error norm is
``|(f1 - f2) . u| / 2``: close to half-Gaussian with sigma = sqrt(2) K / 6 ~ K / 4, i.e. about 68%
of errors below K/4 and 95% below K/2, as the paper reports.

Usage: ``python examples/paper_experiment.py [--frames 100000] [--K 10] [--out paper_hist.png]``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

import torchcontact as tc


def icub_model() -> tc.RobotModel:
    """The iCubGenova04 model from the ``icub-models`` package."""
    import icub_models

    return tc.RobotModel.from_urdf(icub_models.get_model_file("iCubGenova04"))


def run(model: tc.RobotModel, frames: int, K: float, seed: int = 0, link: str = "l_forearm"):
    """Simulate and estimate; returns per-force error norms ``(frames, 2)``, ranks and truth.

    Args:
        model: the robot (a sensor region must contain ``link``).
        frames: number of frames (random joint states and contacts per frame).
        K: maximum force norm, N.
        seed: random seed.
        link: link carrying both contacts.

    Returns:
        dict with ``error`` ``(frames, 2)`` N, ``rank`` and ``unknowns`` ``(frames,)``, ``force``
        and ``truth`` ``(frames, 2, 3)``, ``positions`` ``(frames, 2, 3)``.
    """
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    est = tc.ContactEstimator(model)
    sensor = est.sensor_names[est.region[model.frame(link).body]]
    q, qd, qdd = ((torch.rand(frames, model.nv, generator=g, dtype=f64) * 2 - 1) for _ in range(3))
    # contact points on a 3 cm x 10 cm patch around the link's axis
    pos = (torch.rand(frames, 2, 3, generator=g, dtype=f64) - 0.5) * torch.tensor(
        [0.03, 0.03, 0.1], dtype=f64
    )
    direction = torch.randn(frames, 2, 3, generator=g, dtype=f64)
    direction = direction / direction.norm(dim=-1, keepdim=True)
    norm = torch.rand(frames, 2, 1, generator=g, dtype=f64) * K
    truth = direction * norm
    wrenches = torch.cat((truth, torch.zeros_like(truth)), -1)
    links, kinds = (link, link), ("force", "force")
    ft = est.predict_ft(q, qd, qdd, tc.Contacts(links, ("known",) * 2, pos, wrenches=wrenches))
    r = est.estimate(q, qd, qdd, ft, tc.Contacts(links, kinds, pos))
    return {
        "error": (r.force - truth).norm(dim=-1).numpy(),
        "rank": r.rank[sensor].numpy(),
        "unknowns": r.unknowns[sensor].numpy(),
        "force": r.force.numpy(),
        "truth": truth.numpy(),
        "positions": pos.numpy(),
    }


def summary(error: np.ndarray, K: float) -> dict[str, float]:
    """Fitted half-Gaussian sigma (RMS of the errors) and the shares below K/4 and K/2."""
    e = error.ravel()
    return {
        "sigma_over_K": float(np.sqrt(np.mean(e**2)) / K),
        "below_K_4": float(np.mean(e < K / 4)),
        "below_K_2": float(np.mean(e < K / 2)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--K", type=float, default=10.0)
    ap.add_argument("--out", default="paper_hist.png")
    args = ap.parse_args()
    res = run(icub_model(), args.frames, args.K)
    s = summary(res["error"], args.K)
    print(f"rank {np.unique(res['rank'])} of unknowns {np.unique(res['unknowns'])}")
    print(
        f"sigma = {s['sigma_over_K']:.4f} K (paper: ~K/4; theory sqrt(2)/6 = 0.2357);"
        f" {100 * s['below_K_4']:.1f}% below K/4, {100 * s['below_K_2']:.1f}% below K/2"
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = res["error"].ravel()
    sigma = s["sigma_over_K"] * args.K
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.hist(e, bins=80, density=True, alpha=0.6, label="per-force error norm")
    x = np.linspace(0, e.max(), 300)
    ax.plot(
        x,
        np.sqrt(2 / np.pi) / sigma * np.exp(-(x**2) / (2 * sigma**2)),
        label=f"half-Gaussian, sigma={sigma:.2f} N",
    )
    ax.set_xlabel("error norm (N)")
    ax.set_ylabel("density")
    ax.set_title(f"Two pure forces on the iCub forearm, |f| ~ U[0, {args.K:g}] N, rank 5")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"histogram: {Path(args.out).resolve()}")


if __name__ == "__main__":
    main()
