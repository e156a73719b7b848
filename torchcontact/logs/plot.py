"""PNG plots of an estimated log (matplotlib, Agg backend).

- ``forces.png``: estimated contact forces (link frame, x/y/z) over time, one colour per link,
  with the true forces (``contacts[].true_force``, simulated logs) as black dots when present.
- ``quality.png``: per-frame rank and number of unknowns, and the residual ``|A x* - b|``, per
  sensor; frames whose status is not ``ok`` marked in red.
- ``robot.png``: the robot at one frame (links as segments between body origins of a forward
  pass) with the contact forces as arrows, like Figure 2 of Del Prete et al. 2012. Needs the
  joint positions: from the input log (``input_log``) joined on ``t_ns``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["plot_log"]


def _flat_contacts(tab: Any) -> dict[str, np.ndarray]:
    import pyarrow.compute as pc

    lst = tab.column("contacts").combine_chunks()
    parent = pc.list_parent_indices(lst).to_numpy(zero_copy_only=False)
    st = lst.flatten()
    names = [f.name for f in st.type]
    cols = dict(zip(names, st.flatten(), strict=True))
    from torchcontact.logs.format import vectors

    out = {
        "frame": parent,
        "link": np.asarray(cols["link"].to_pylist(), dtype=object),
        "position": vectors(cols["position"], 3)[0],
        "force": vectors(cols["force"], 3)[0],
    }
    if "true_force" in cols:
        out["true_force"] = vectors(cols["true_force"], 3)[0]
    return out


def plot_log(
    log: str | Path,
    robot: str | Path,
    out_dir: str | Path,
    *,
    frame: int | None = None,
    input_log: str | Path | None = None,
) -> list[Path]:
    """Write ``forces.png``, ``quality.png`` and ``robot.png`` for an estimated log.

    Args:
        log: output of :func:`torchcontact.logs.estimate_file`.
        robot: the URDF the log was estimated with.
        out_dir: folder for the PNGs (created).
        frame: row index of the 3D view (default: the largest total contact force).
        input_log: the input log, for the joint positions of the 3D view (skipped without it).

    Returns:
        Paths of the PNGs written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pyarrow.parquet as pq

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tab = pq.read_table(log)
    t = (tab.column("t_ns").to_numpy() - tab.column("t_ns")[0].as_py()) * 1e-9
    status = np.asarray(tab.column("status").to_pylist(), dtype=object)
    fc = _flat_contacts(tab)
    written = []

    # ---- contact forces over time, per link, with the truth
    fig, axes = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    links = sorted(set(fc["link"].tolist()) - {None})
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, ax in enumerate(axes):
        for j, link in enumerate(links):
            sel = fc["link"] == link
            ax.plot(
                t[fc["frame"][sel]],
                fc["force"][sel, i],
                ".",
                ms=2,
                color=colors[j % len(colors)],
                label=f"{link} (estimate)" if i == 0 else None,
            )
        if "true_force" in fc:
            ax.plot(
                t[fc["frame"]],
                fc["true_force"][:, i],
                ".",
                ms=0.6,
                color="k",
                label="truth" if i == 0 else None,
            )
        ax.set_ylabel(f"f{'xyz'[i]} [N]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=7, markerscale=4)
    axes[0].set_title("Contact forces (link frame)")
    axes[-1].set_xlabel("time [s]")
    fig.tight_layout()
    written.append(out_dir / "forces.png")
    fig.savefig(written[-1], dpi=110)
    plt.close(fig)

    # ---- rank / unknowns / residual per sensor
    sensors = [c[5:] for c in tab.column_names if c.startswith("rank.")]
    fig, axes = plt.subplots(2, 1, figsize=(10, 5), sharex=True)
    bad = status != "ok"
    for s in sensors:
        axes[0].step(t, tab.column(f"rank.{s}").to_numpy(), where="post", label=f"rank {s}")
        axes[0].step(
            t, tab.column(f"unknowns.{s}").to_numpy(), "--", where="post", label=f"unknowns {s}"
        )
        r = tab.column(f"residual.{s}").to_numpy(zero_copy_only=False)
        axes[1].semilogy(t, np.maximum(r, 1e-16), lw=0.8, label=f"residual {s}")
    if bad.any():
        axes[0].plot(t[bad], np.zeros(bad.sum()), "rx", ms=4, label="status != ok")
    axes[0].set_ylabel("count")
    axes[1].set_ylabel("|A x - b|")
    axes[1].set_xlabel("time [s]")
    for ax in axes:
        ax.legend(loc="upper right", fontsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    written.append(out_dir / "quality.png")
    fig.savefig(written[-1], dpi=110)
    plt.close(fig)

    if input_log is not None:
        written.append(_robot_view(tab, fc, robot, input_log, frame, out_dir / "robot.png"))
    return written


def _robot_view(tab, fc, robot, input_log, frame, path: Path) -> Path:
    import matplotlib.pyplot as plt
    import pyarrow.parquet as pq
    import torch

    import torchcontact as tc
    from torchcontact.logs.format import joint_names_of, vectors

    model = tc.RobotModel.from_urdf(robot)
    if frame is None:  # the frame with the largest total contact force
        mag = np.linalg.norm(np.nan_to_num(fc["force"]), axis=-1)
        frame = int(np.argmax(np.bincount(fc["frame"], mag, minlength=tab.num_rows)))
    t_ns = tab.column("t_ns")[frame].as_py()
    inp = pq.read_table(input_log, columns=["t_ns", "q"], filters=[("t_ns", "==", t_ns)])
    names = joint_names_of(pq.read_schema(input_log))
    q, _ = vectors(inp.column("q"), len(names))
    q = q[0, [names.index(n) for n in model.joint_names]]
    zero = torch.zeros(model.nv, dtype=model.dtype)
    fp = tc.forward_pass(model, torch.as_tensor(q), zero, zero)
    p = fp.p.numpy()
    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    for b in range(1, model.nb):  # links as segments between body origins
        a = p[model.body_parent[b]]
        ax.plot(*np.stack([a, p[b]]).T, "-o", color="0.3", lw=3, ms=4)
    sel = np.flatnonzero(fc["frame"] == frame)
    scale = 0.02  # m per N
    for i in sel:
        R, pf = model.frame_pose(fp, fc["link"][i])
        R, pf = R.numpy(), pf.numpy()
        c = R @ fc["position"][i] + pf
        f = R @ np.nan_to_num(fc["force"][i])
        ax.scatter(*c, color="tab:red", s=20)
        ax.quiver(*c, *(f * scale), color="tab:red", lw=2, label="estimate")
        if "true_force" in fc:
            ft = R @ fc["true_force"][i]
            ax.quiver(*c, *(ft * scale), color="k", lw=1, linestyle="--", label="truth")
    lim = np.abs(p).max() + 0.1
    ax.set(xlim=(-lim, lim), ylim=(-lim, lim), zlim=(0, 2 * lim))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title(f"frame {frame}: {len(sel)} contact(s), arrows {scale * 1000:.0f} mm/N")
    handles, labels = ax.get_legend_handles_labels()
    uniq = dict(zip(labels, handles, strict=True))
    if uniq:
        ax.legend(uniq.values(), uniq.keys(), loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
