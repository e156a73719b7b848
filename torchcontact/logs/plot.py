"""PNG plots of an estimated log (matplotlib, Agg backend), and what every view of a log draws.

- ``forces.png``: per contact slot (one colour each), the estimated contact force and moment
  (link frame, x/y/z) over time as dots, and the truth (``contacts[].true_force``, simulated logs)
  as a line of the same colour. Frames where some sensor's rank is below its number of unknowns
  are shaded: the sensors do not determine the forces there (the estimate is the minimum-norm
  solution, or with ``--constraints`` the friction-cone constrained one), so it cannot recover the
  truth.
- ``quality.png``: per sensor, the rank and the number of unknowns, and the residual
  ``|A x* - b|``; frames with a non-zero status are marked per status bit (by name); with
  ``--constraints`` a third panel shows the interior-point iterations, the frames that did not
  converge and the number of contacts whose cone is active.
- ``robot.png``: the robot at one frame (links as segments between body origins of a forward pass)
  with the contact forces as arrows, like Figure 2 of Del Prete et al. 2012. The view fits the
  robot; by default the frame is a well-posed one (every sensor's rank equals its unknowns) with
  the largest force. Needs the joint positions: from the input log (``input_log``), same rows.
- ``nullspace.png``: the unobservable directions of one frame (default: the frame with the most):
  per sensor, an orthonormal basis of the null space of ``A`` among its region's unknowns
  (:attr:`ContactEstimate.nullspace`, recomputed from the frame's joint positions and contacts),
  each basis vector drawn as forces (and moments) at the contacts on the robot, and all of them
  as a table of components by unknown (each cell with its value). Also needs the input log.

Legends sit outside the axes.

What is drawn, shared with the rerun recording of :mod:`torchcontact.view`: the contact slots and
their colours (:func:`contact_slots`, :func:`slot_rgb`), the truth's opacity
(:data:`TRUTH_ALPHA`), the ill-posed frames and their grey (:func:`rank_deficient`,
:data:`ILL_POSED_RGB`, :func:`ill_posed_note`), the status bits by name
(:data:`torchcontact.status.STATUS_NAMES`) and the null-space directions of a frame
(:func:`null_directions`).
"""

from __future__ import annotations

import json
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torchcontact.errors import InputError, LogError

__all__ = [
    "ILL_POSED_RGB",
    "SLOT_COLORS",
    "TRUTH_ALPHA",
    "NullDirection",
    "contact_slots",
    "ill_posed_note",
    "null_directions",
    "plot_log",
    "rank_deficient",
    "slot_label",
    "slot_rgb",
]

# ---------------------------------------------------------------------- what is drawn
#: Colour of contact slot ``k``: ``SLOT_COLORS[k % 10]``, RGB 0-255 (matplotlib's ``tab10``
#: cycle): the estimate and the truth of one slot share it, in the PNGs and in the rerun view.
SLOT_COLORS: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
)
#: Opacity of the truth (lines in ``forces.png``, arrows in the rerun view); the estimate is opaque.
TRUTH_ALPHA = 0.55
#: Grey of the frames where some sensor's rank is below its unknowns (shading, timeline lane).
ILL_POSED_RGB = (224, 224, 224)
#: Colour of the null-space directions (``nullspace.png``, rerun view).
NULLSPACE_RGB = (148, 103, 189)
#: Colour of a non-zero status (markers in ``quality.png``, the status lane of the rerun view).
BAD_STATUS_RGB = (214, 39, 40)


def slot_rgb(k: int, alpha: float = 1.0) -> tuple[int, int, int, int]:
    """RGBA 0-255 of contact slot ``k`` (``alpha`` 0-1: :data:`TRUTH_ALPHA` for the truth).

    Example:
        >>> slot_rgb(0), slot_rgb(10, TRUTH_ALPHA)
        ((31, 119, 180, 255), (31, 119, 180, 140))
    """
    return (*SLOT_COLORS[k % len(SLOT_COLORS)], int(round(255 * alpha)))


def _mpl(rgb: Sequence[int]) -> tuple[float, ...]:
    """0-255 RGB(A) -> matplotlib's 0-1 floats."""
    return tuple(c / 255 for c in rgb)


def contact_slots(records: Any, layout: Any = None) -> tuple[Any, np.ndarray]:
    """The contact slots of a log's records: what one colour stands for.

    Slot ``k`` of the layout that covers every frame (:meth:`SlotLayout.covering`: per ``(link,
    kind)`` pair, sorted, as many slots as the most records of that pair in one frame) holds the
    ``r``-th record of its pair in each frame, so two contacts on one link are two slots.

    Args:
        records: :class:`~torchcontact.contacts.ContactRecords`.
        layout: a :class:`~torchcontact.contacts.SlotLayout` that covers them (default: the
            covering of ``records``; a streamed log passes the covering of all its chunks).

    Returns:
        ``(layout, slot)``: the layout and ``(M,)`` int64 slot per record (-1: no link or an
        unknown kind, not drawn).
    """
    from torchcontact.contacts import SlotLayout

    if layout is None:
        layout = SlotLayout.covering(records)
    return layout, layout.assign(records)


def slot_label(layout: Any, k: int) -> str:
    """``"slot k: link"`` (with the record's rank on its link when the link has several slots).

    Example:
        >>> from torchcontact.contacts import SlotLayout
        >>> lay = SlotLayout(("a", "b", "b"), ("force",) * 3)
        >>> slot_label(lay, 0), slot_label(lay, 2)
        ('slot 0: a', 'slot 2: b #2')
    """
    link, kind = layout.links[k], layout.kinds[k]
    same = [i for i, pair in enumerate(zip(layout.links, layout.kinds, strict=True))
            if pair == (link, kind)]  # fmt: skip
    kinds = {kd for ln, kd in zip(layout.links, layout.kinds, strict=True) if ln == link}
    text = f"slot {k}: {link}" + (f" ({kind})" if len(kinds) > 1 else "")
    return text + (f" #{same.index(k) + 1}" if len(same) > 1 else "")


def rank_deficient(
    rank: Mapping[str, np.ndarray], unknowns: Mapping[str, np.ndarray]
) -> np.ndarray:
    """``(N,)`` bool: frames where some sensor's rank is below its number of unknowns.

    There the sensors do not determine the contact forces (a null space of ``A`` remains), and the
    estimate cannot recover the truth: shaded in the PNGs, a grey lane in the rerun view.

    Args:
        rank: sensor -> ``(N,)`` rank of ``A``.
        unknowns: sensor -> ``(N,)`` number of unknowns.
    """
    out = None
    for s in rank:
        d = np.asarray(rank[s]) < np.asarray(unknowns[s])
        out = d if out is None else out | d
    return np.zeros(0, bool) if out is None else out


def ill_posed_note(constrained: bool) -> str:
    """What an ill-posed frame's estimate is (caption of the shading and of the timeline lane).

    Args:
        constrained: the estimate was made with ``--constraints`` (friction cones).
    """
    what = "the friction-cone constrained estimate" if constrained else "the minimum-norm estimate"
    return f"rank < unknowns: the sensors do not determine the forces, {what} need not be the truth"


def _rank_deficient(tab: Any, sensors: list[str]) -> np.ndarray:
    return rank_deficient(
        {s: tab.column(f"rank.{s}").to_numpy() for s in sensors},
        {s: tab.column(f"unknowns.{s}").to_numpy() for s in sensors},
    )


def _constrained(tab: Any) -> bool:
    """The estimate was made with ``--constraints`` (it has ``converged.<sensor>`` columns)."""
    return any(c.startswith("converged.") for c in tab.column_names)


def _flat_contacts(tab: Any) -> dict[str, Any]:
    from torchcontact.logs.format import read_contacts, vectors

    records, fields, _ = read_contacts(tab.column("contacts"))
    layout, slot = contact_slots(records)
    out = {
        "frame": records.frame,
        "link": records.links,
        "position": records.positions,
        "force": vectors(fields["force"], 3)[0],
        "moment": vectors(fields["moment"], 3)[0],
        "slot": slot,
        "layout": layout,
    }
    for name in ("true_force", "true_moment"):
        if name in fields:
            out[name] = vectors(fields[name], 3)[0]
    if "cone_active" in fields:
        out["cone_active"] = np.asarray(
            fields["cone_active"].fill_null(False).to_numpy(zero_copy_only=False), bool
        )
    return out


def _shade(ax: Any, t: np.ndarray, mask: np.ndarray) -> None:
    if mask.any():
        ax.fill_between(t, 0, 1, where=mask, step="post", color=_mpl(ILL_POSED_RGB),
                        transform=ax.get_xaxis_transform(), lw=0)  # fmt: skip


def _with_gaps(t: np.ndarray, frame: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Break a line where consecutive records are not consecutive frames."""
    if len(frame) < 2:
        return t[frame], y
    gap = np.flatnonzero(np.diff(frame) != 1) + 1
    return np.insert(t[frame].astype(float), gap, np.nan), np.insert(y, gap, np.nan)


def _load(log: str | Path, robot: Any) -> tuple[Any, Any]:
    from torchcontact.logs.format import META_URDF_SHA256, open_log
    from torchcontact.logs.pipeline import load_robot

    pf = open_log(log)
    names = pf.schema_arrow.names
    need = ["t_ns", "contacts", "status_code", "status"]
    missing = [c for c in need if c not in names]
    if missing or not any(c.startswith("rank.") for c in names):
        raise LogError(
            f"{log}: not an output of torchcontact estimate (missing {missing or ['rank.*']}; plot"
            " the estimate, and give the input log with --input)"
        )
    if pf.metadata.num_rows == 0:
        raise LogError(f"{log}: no frames to plot")
    model = load_robot(robot)
    logged = (pf.schema_arrow.metadata or {}).get(META_URDF_SHA256, b"").decode()
    if logged and logged != model.urdf_sha256:
        raise LogError(
            f"{log}: estimated with another robot (URDF sha256 {logged[:12]}...), not"
            f" {model.name} ({model.urdf_sha256[:12]}...); pass that URDF with --robot"
        )
    try:
        tab = pf.read()
    except Exception as exc:
        raise LogError(f"{log}: corrupted data ({exc})") from None
    return tab, model


def plot_log(
    log: str | Path,
    robot: str | Path,
    out_dir: str | Path,
    *,
    frame: int | None = None,
    input_log: str | Path | None = None,
    progress: bool = False,
) -> list[Path]:
    """Write ``forces.png``, ``quality.png``, ``robot.png`` and ``nullspace.png`` for an estimate.

    Args:
        log: output of :func:`torchcontact.logs.estimate_file`.
        robot: the URDF the log was estimated with.
        out_dir: folder for the PNGs (created).
        frame: row index of the robot view and of the unobservable directions (default: a
            well-posed frame with the largest force for the robot view, the frame with the most
            unobservable directions for ``nullspace.png``).
        input_log: the input log, for the joint positions of the robot view and of the
            unobservable directions (both skipped without it).
        progress: show a progress bar over the figures.

    Returns:
        Paths of the PNGs written.

    Raises:
        LogError: not an estimate, an empty log, another robot's estimate, an input log whose
            rows are not the estimate's.
        InputError: ``frame`` outside the log, an output that is an input.
    """
    import matplotlib

    matplotlib.use("Agg")
    from tqdm import tqdm

    from torchcontact.logs.format import check_outputs

    out_dir = Path(out_dir)
    names = ["forces.png", "quality.png"]
    names += ["robot.png", "nullspace.png"] if input_log is not None else []
    check_outputs([out_dir / n for n in names], [log, input_log, robot])
    tab, model = _load(log, robot)
    if frame is not None and not 0 <= frame < tab.num_rows:
        raise InputError(f"--frame {frame}: the log has rows 0..{tab.num_rows - 1}")
    out_dir.mkdir(parents=True, exist_ok=True)
    t_ns = tab.column("t_ns").to_numpy()
    t = (t_ns - t_ns[0]) * 1e-9
    sensors = json.loads((tab.schema.metadata or {}).get(b"torchcontact.sensors", b"[]"))
    sensors = sensors or [c[5:] for c in tab.column_names if c.startswith("rank.")]
    fc = _flat_contacts(tab)
    deficient = _rank_deficient(tab, sensors)
    constrained = _constrained(tab)
    written = []
    with tqdm(total=len(names), unit="png", desc="plot", disable=not progress) as bar:
        written.append(_forces(t, fc, deficient, constrained, out_dir / "forces.png"))
        bar.update(1)
        written.append(
            _quality(t, tab, sensors, deficient, constrained, fc, out_dir / "quality.png")
        )
        bar.update(1)
        if input_log is not None:
            written.append(
                _robot_view(tab, fc, model, input_log, frame, deficient, out_dir / "robot.png")
            )
            bar.update(1)
            written.append(
                _nullspace_view(tab, model, sensors, input_log, frame, out_dir / "nullspace.png")
            )
            bar.update(1)
    return written


def _ill_posed_patch(constrained: bool) -> Any:
    from matplotlib.patches import Patch

    return Patch(color=_mpl(ILL_POSED_RGB), label=textwrap.fill(ill_posed_note(constrained), 26))


def _forces(t: np.ndarray, fc: dict, deficient: np.ndarray, constrained: bool, path: Path) -> Path:
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    fig, axes = plt.subplots(3, 2, figsize=(13, 7.5), sharex=True)
    layout = fc["layout"]
    handles: list[Any] = []
    for k in range(layout.K):
        c = _mpl(slot_rgb(k))
        sel = np.flatnonzero(fc["slot"] == k)  # at most one record per frame
        frames = fc["frame"][sel]
        for col, what in enumerate(("force", "moment")):
            truth = fc.get(f"true_{what}")
            for i in range(3):
                ax = axes[i, col]
                if truth is not None:
                    x, y = _with_gaps(t, frames, truth[sel, i])
                    ax.plot(x, y, "-", color=c, lw=1.2, alpha=TRUTH_ALPHA)
                ax.plot(t[frames], fc[what][sel, i], ".", color=c, ms=2.5)
        label = slot_label(layout, k)
        handles.append(Line2D([], [], color=c, marker=".", ls="", ms=8, label=f"{label} estimate"))
        if "true_force" in fc:
            handles.append(
                Line2D([], [], color=c, lw=1.2, alpha=TRUTH_ALPHA, label=f"{label} truth")
            )
    for i in range(3):
        for col, (sym, unit) in enumerate((("f", "N"), ("m", "N m"))):
            ax = axes[i, col]
            _shade(ax, t, deficient)
            ax.set_ylabel(f"{sym}{'xyz'[i]} [{unit}]")
            ax.grid(alpha=0.3)
    axes[0, 0].set_title("force (link frame)")
    axes[0, 1].set_title("moment about the contact point (link frame)")
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    if deficient.any():
        handles.append(_ill_posed_patch(constrained))
    kind = "friction-cone constrained estimate" if constrained else "estimate"
    title = f"Contact wrenches per slot: {kind} (dots) and truth (lines); shaded: "
    fig.suptitle(textwrap.fill(title + ill_posed_note(constrained), 150), fontsize=10)
    fig.tight_layout(rect=(0, 0, 0.8, 1))
    fig.legend(handles=handles, loc="center left", bbox_to_anchor=(0.8, 0.5), fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _status_marks(ax: Any, t: np.ndarray, codes: np.ndarray) -> None:
    """One marker row per status bit present, labelled with its name (:data:`STATUS_NAMES`)."""
    from torchcontact.status import STATUS, STATUS_NAMES, WARNINGS

    present = [bit for bit in STATUS if (codes & bit).any()]
    for j, bit in enumerate(present):
        hit = (codes & bit) != 0
        ax.plot(t[hit], np.full(hit.sum(), -0.3 * (j + 1)), "x", color=_mpl(BAD_STATUS_RGB),
                ms=4, alpha=1 - 0.6 * j / max(len(present), 1),
                label=f"status {STATUS_NAMES.get(bit, bit)} ({bit}): "
                      + ("last iterate" if bit == 256
                         else "outputs kept" if bit & WARNINGS else "NaN outputs"))  # fmt: skip


def _quality(
    t: np.ndarray,
    tab: Any,
    sensors: list[str],
    deficient: np.ndarray,
    constrained: bool,
    fc: dict,
    path: Path,
) -> Path:
    import matplotlib.pyplot as plt

    rows = 3 if constrained else 2
    fig, axes = plt.subplots(rows, 1, figsize=(12, 2.75 * rows), sharex=True)
    for s in sensors:
        axes[0].step(t, tab.column(f"unknowns.{s}").to_numpy(), where="post", lw=2.5, alpha=0.5,
                     label=f"unknowns {s}")  # fmt: skip
        axes[0].step(t, tab.column(f"rank.{s}").to_numpy(), where="post", lw=1, label=f"rank {s}")
        r = tab.column(f"residual.{s}").to_numpy(zero_copy_only=False)
        axes[1].semilogy(t, np.maximum(r, 1e-16), lw=0.8, label=f"residual {s}")
    _status_marks(axes[0], t, tab.column("status_code").to_numpy())
    if constrained:
        ax = axes[2]
        for s in sensors:
            it = tab.column(f"iterations.{s}").to_numpy(zero_copy_only=False).astype(float)
            ax.step(t, it, where="post", lw=0.8, label=f"iterations {s}")
            conv = tab.column(f"converged.{s}").to_numpy(zero_copy_only=False)
            bad = conv == False  # noqa: E712 (null: a frame not solved)
            if bad.any():
                ax.plot(t[bad], it[bad], "x", color=_mpl(BAD_STATUS_RGB), ms=4,
                        label=f"not converged {s}")  # fmt: skip
        if "cone_active" in fc:
            active = np.bincount(fc["frame"], fc["cone_active"], minlength=len(t))
            ax.step(t, active, where="post", lw=1.5, color="k", alpha=0.6,
                    label="contacts with an active cone")  # fmt: skip
        ax.set_ylabel("count")
        ax.set_title("Friction cones (interior point)", fontsize=10)
    for ax in axes:
        _shade(ax, t, deficient)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("count")
    axes[1].set_ylabel("|A x - b|")
    axes[-1].set_xlabel("time [s]")
    title = "Identifiability per sensor; shaded: " + ill_posed_note(constrained)
    axes[0].set_title(textwrap.fill(title, 110), fontsize=10)
    fig.tight_layout(rect=(0, 0, 0.78, 1))
    for ax in axes:
        h, labels = ax.get_legend_handles_labels()
        if ax is axes[0] and deficient.any():
            h.append(_ill_posed_patch(constrained))
            labels.append("rank < unknowns")
        ax.legend(h, labels, loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _default_frame(tab: Any, fc: dict, deficient: np.ndarray) -> int:
    """A well-posed frame (status 0, rank = unknowns, a contact) with the largest force."""
    mag = np.linalg.norm(np.nan_to_num(fc["force"]), axis=-1)
    total = np.bincount(fc["frame"], mag, minlength=tab.num_rows)
    ok = (tab.column("status_code").to_numpy() == 0) & ~deficient & (total > 0)
    if ok.any():
        return int(np.flatnonzero(ok)[np.argmax(total[ok])])
    return int(np.argmax(total))


def _side_view(vectors: list[np.ndarray]) -> tuple[float, float]:
    """Camera ``(elevation, azimuth)`` in degrees that sees the vectors most from the side."""
    dirs = [v / np.linalg.norm(v) for v in vectors if np.linalg.norm(v) > 0]
    if not dirs:
        return 25.0, -60.0
    best, view = np.inf, (25.0, -60.0)
    for elev in (15.0, 25.0, 35.0):
        for azim in np.arange(-180.0, 180.0, 10.0):
            e, a = np.radians(elev), np.radians(azim)
            cam = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            worst = max(abs(float(cam @ d)) for d in dirs)
            if worst < best - 1e-9:
                best, view = worst, (elev, float(azim))
    return view


def _posed(tab: Any, model: Any, input_log: str | Path, frame: int) -> tuple[Any, Any]:
    """Joint positions ``(nv,)`` and forward pass of the estimate's row ``frame``.

    The positions come from the input log (same rows), in the model's joint order.

    Raises:
        LogError: the input log lacks the robot's joints, has other rows, or another ``t_ns``.
    """
    import torch

    import torchcontact as tc
    from torchcontact.logs.format import (
        joint_names_of,
        joint_permutation,
        open_log,
        read_rows,
        vectors,
    )

    t_ns = tab.column("t_ns")[frame].as_py()
    pf = open_log(input_log)
    names = joint_names_of(pf.schema_arrow, input_log)
    perm = joint_permutation(names, model.joint_names, model.name, input_log)  # extra: a warning
    if pf.metadata.num_rows != tab.num_rows:
        raise LogError(
            f"{input_log}: {pf.metadata.num_rows} rows, the estimate has {tab.num_rows}: give the"
            " log that was estimated"
        )
    row = read_rows(input_log, frame, frame + 1, ["t_ns", "q"])
    if row.column("t_ns")[0].as_py() != t_ns:
        raise LogError(f"{input_log}: row {frame} has another t_ns than the estimate's")
    q, _ = vectors(row.column("q"), len(names))
    q = q[0, perm]
    q = torch.as_tensor(q, dtype=model.dtype)
    zero = torch.zeros(model.nv, dtype=model.dtype)
    return q, tc.forward_pass(model, q, zero, zero)


def _draw_robot(ax: Any, model: Any, p: np.ndarray) -> None:
    """Links as segments between body origins (world frame)."""
    for b in range(1, model.nb):
        a = p[model.body_parent[b]]
        ax.plot(*np.stack([a, p[b]]).T, "-o", color="0.35", lw=3, ms=4)


def _fit_view(ax: Any, pts: list[np.ndarray], arrows: list[np.ndarray]) -> None:
    """Equal axes around ``pts``, seen from the side of the arrows."""
    allp = np.concatenate(pts)
    mid, half = (allp.min(0) + allp.max(0)) / 2, (allp.max(0) - allp.min(0)).max() / 2 + 0.05
    ax.set(xlim=(mid[0] - half, mid[0] + half), ylim=(mid[1] - half, mid[1] + half))
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(*_side_view(arrows))
    # few, small ticks: the labels of a small 3-D view overlap otherwise
    from matplotlib.ticker import MaxNLocator

    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_major_locator(MaxNLocator(3))
    ax.tick_params(labelsize=7, pad=0)
    ax.set_xlabel("x [m]", fontsize=8, labelpad=-2)
    ax.set_ylabel("y [m]", fontsize=8, labelpad=-2)
    ax.set_zlabel("z [m]", fontsize=8, labelpad=-2)


def _robot_view(
    tab: Any,
    fc: dict,
    model: Any,
    input_log: str | Path,
    frame: int | None,
    deficient: np.ndarray,
    path: Path,
) -> Path:
    import matplotlib.pyplot as plt

    if frame is None:
        frame = _default_frame(tab, fc, deficient)
    t_ns = tab.column("t_ns")[frame].as_py()
    _, fp = _posed(tab, model, input_log, frame)
    p = fp.p.numpy()
    sel = np.flatnonzero(fc["frame"] == frame)
    arrows = []  # (slot, point, estimate, truth) in the world frame
    for i in sel:
        R, pf_ = (x.numpy() for x in model.frame_pose(fp, fc["link"][i]))
        c = R @ fc["position"][i] + pf_
        truth = R @ fc["true_force"][i] if "true_force" in fc else None
        arrows.append((int(fc["slot"][i]), c, R @ np.nan_to_num(fc["force"][i]), truth))
    # arrows: the largest force spans 30 % of the robot's size
    lo, hi = p.min(0), p.max(0)
    size = max(float(np.max(hi - lo)), 0.2)
    fmax = max([np.linalg.norm(a[2]) for a in arrows] + [np.linalg.norm(a[3]) for a in arrows
               if a[3] is not None] + [1e-9])  # fmt: skip
    scale = 0.3 * size / fmax  # m per N
    fig = plt.figure(figsize=(7.5, 7))
    ax = fig.add_subplot(projection="3d")
    _draw_robot(ax, model, p)
    pts = [p]
    for k, c, f, truth in arrows:
        color, label = _mpl(slot_rgb(max(k, 0))), slot_label(fc["layout"], k) if k >= 0 else "?"
        ax.scatter(*c, color=color, s=25, depthshade=False)
        ax.quiver(*c, *(f * scale), color=color, lw=2.5, label=f"{label} estimate")
        pts += [c[None], (c + f * scale)[None]]
        if truth is not None:
            ax.quiver(*c, *(truth * scale), color=color, alpha=TRUTH_ALPHA, lw=1.2,
                      linestyle="--", label=f"{label} truth")  # fmt: skip
            pts.append((c + truth * scale)[None])
    _fit_view(ax, pts, [a[2] for a in arrows])
    posed = "well-posed" if not deficient[frame] else ill_posed_note(_constrained(tab))
    title = (
        f"t = {(t_ns - tab.column('t_ns')[0].as_py()) * 1e-9:.2f} s (row {frame}), {len(sel)}"
        f" contact(s), {posed}"
    )
    ax.set_title(
        textwrap.fill(title, 80) + f"\narrows: {scale * 1000:.0f} mm per N, world frame",
        fontsize=10,
    )
    handles, labels = ax.get_legend_handles_labels()
    uniq = dict(zip(labels, handles, strict=True))
    if uniq:
        fig.legend(uniq.values(), uniq.keys(), loc="lower center", ncol=2, fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


#: Most null-space directions drawn (each its own 3-D view).
MAX_DIRECTIONS = 6


def _nullity(tab: Any, sensors: list[str]) -> np.ndarray:
    """``(N, S)`` null-space dimensions (``nullity.<s>``, else ``unknowns - rank``)."""
    cols = []
    for s in sensors:
        if f"nullity.{s}" in tab.column_names:
            cols.append(tab.column(f"nullity.{s}").to_numpy(zero_copy_only=False))
        else:
            cols.append(tab.column(f"unknowns.{s}").to_numpy() - tab.column(f"rank.{s}").to_numpy())
    return np.stack(cols, -1).astype(float)


@dataclass(frozen=True)
class NullDirection:
    """One basis vector of the null space of a sensor's ``A`` at one frame, drawn as contact forces.

    Attributes:
        sensor: the sensor whose region it belongs to.
        index: ``j``, the basis vector's column in :attr:`ContactEstimate.nullspace`.
        nullity: the dimension of that null space at the frame.
        parts: per slot of the region, ``(point, force, moment or None)`` in the world frame: the
            contact point (m) and the unit basis vector's components there as a force and, for a
            ``wrench`` contact, a moment (N, N m). Adding any multiple of them to the contact
            forces changes no reading of the sensor.
    """

    sensor: str
    index: int
    nullity: int
    parts: tuple[tuple[np.ndarray, np.ndarray, np.ndarray | None], ...]


def null_directions(
    model: Any, sensors: Sequence[str], q: Any, records: Any, rows: Sequence[int] | None = None
) -> list[tuple[list[NullDirection], dict[str, list[str]], dict[str, np.ndarray]]]:
    """The null-space bases of frames as contact forces in the world frame (batched).

    Recomputes :attr:`ContactEstimate.nullspace` (it depends on the joint positions and the
    contacts only) for each frame's contacts (``known`` ones have no unknowns and are left out),
    one batched estimate per distinct set of contact links and kinds.

    Args:
        model: the robot.
        sensors: the estimate's sensors.
        q: ``(N, nv)`` joint positions (numpy or torch), model order.
        records: :class:`~torchcontact.contacts.ContactRecords` of frames ``0 .. N-1``.
        rows: the frames' rows in their log, for messages (default ``0 .. N-1``).

    Returns:
        Per frame ``(directions, labels, bases)``: every :class:`NullDirection` of every sensor,
        the labels of each sensor's unknowns (:meth:`ContactEstimator.unknown_labels`) and its
        basis ``(unknowns, nullity)``.

    Raises:
        LogError: a frame's contacts cannot be laid out (an unknown link or kind).
    """
    import torch

    import torchcontact as tc
    from torchcontact.errors import TorchContactError

    q = torch.as_tensor(np.asarray(q), dtype=model.dtype)
    N = q.shape[0]
    rows = list(range(N)) if rows is None else list(rows)
    keep = np.array([isinstance(k, str) and k in tc.KINDS and k != "known" for k in records.kinds],
                    bool)  # fmt: skip
    records = records.select(keep)
    groups: dict[tuple, list[int]] = {}  # frames with the same contact set: one batch
    sig = [[] for _ in range(N)]
    for link, kind, f in zip(records.links, records.kinds, records.frame, strict=True):
        sig[f].append((str(link), str(kind)))
    for f in range(N):
        groups.setdefault(tuple(sorted(sig[f])), []).append(f)
    est = tc.ContactEstimator(model, list(sensors))
    out: list[Any] = [None] * N
    for frames in groups.values():
        G, index = len(frames), np.full(N, -1)
        index[frames] = np.arange(G)
        sub = records.select(index[records.frame] >= 0).with_frame(
            index[records.frame[index[records.frame] >= 0]]
        )
        qg = q[frames]
        try:
            contacts, _ = tc.Contacts.from_records(sub, G, dtype=model.dtype)
            zero = torch.zeros_like(qg)
            ft = {s: qg.new_zeros(G, 6) for s in sensors}
            res = est.estimate(qg, zero, zero, ft, contacts, nullspace=True, backend="eager")
            labels = est.unknown_labels(contacts)
        except TorchContactError as exc:
            raise LogError(
                f"row {rows[frames[0]]}: no null space for its contacts ({exc})"
            ) from None
        fp = tc.forward_pass(model, qg, torch.zeros_like(qg), torch.zeros_like(qg))
        em = est.layout(contacts.links, contacts.kinds)
        poses = {ln: [a.numpy() for a in model.frame_pose(fp, ln)] for ln in set(contacts.links)}
        for g, f in enumerate(frames):
            dirs, bases = [], {}
            for s, reg in zip(sensors, em.regions, strict=True):
                d = int(res.nullity[s][g])
                bases[s] = res.nullspace[s][g, :, :d].numpy()
                for j in range(d):
                    v, start, parts = bases[s][:, j], 0, []
                    for k in reg.slots:
                        kind = em.slots[k].kind
                        x = v[start : start + tc.KINDS[kind]]
                        start += tc.KINDS[kind]
                        if kind == "force_dir":
                            u = contacts.directions[g, k].numpy()
                            fk, mk = x[0] * u / max(np.linalg.norm(u), 1e-12), None
                        else:
                            fk, mk = x[:3], (x[3:] if kind == "wrench" else None)
                        R, pk = (a[g] for a in poses[contacts.links[k]])
                        c = R @ contacts.positions[g, k].numpy() + pk
                        parts.append((c, R @ fk, None if mk is None else R @ mk))
                    dirs.append(NullDirection(s, j, d, tuple(parts)))
            out[f] = (dirs, labels, bases)
    return out


def _null_directions(
    tab: Any, model: Any, sensors: list[str], q: Any, fp: Any, frame: int
) -> tuple[list[tuple], dict[str, list[str]], dict[str, np.ndarray]]:
    """:func:`null_directions` of row ``frame`` of an estimate (``q``: its ``(nv,)`` positions).

    Returns:
        ``(sensor, j, nullity, parts)`` per basis vector, the labels, the bases.
    """
    from torchcontact.logs.format import read_contacts

    records, _, _ = read_contacts(tab.column("contacts").slice(frame, 1))
    [(dirs, labels, bases)] = null_directions(model, sensors, q[None], records, [frame])
    return [(d.sensor, d.index, d.nullity, list(d.parts)) for d in dirs], labels, bases


def _nullspace_view(
    tab: Any, model: Any, sensors: list[str], input_log: str | Path, frame: int | None, path: Path
) -> Path:
    """The unobservable directions of one frame: null-space basis vectors as contact forces.

    Each basis vector (of :attr:`ContactEstimate.nullspace`) is drawn at the contacts, world
    frame, its largest force 25 % of the robot's size, with a table of its components by unknown.
    Default frame: the one with the most unobservable directions among those with status 0.
    """
    import matplotlib.pyplot as plt

    if frame is None:
        nullity = np.nan_to_num(_nullity(tab, sensors)).sum(-1)
        nullity[tab.column("status_code").to_numpy() != 0] = -1
        frame = int(np.argmax(nullity))
    q, fp = _posed(tab, model, input_log, frame)
    p = fp.p.numpy()
    dirs, labels, bases = _null_directions(tab, model, sensors, q, fp, frame)
    shown = dirs[:MAX_DIRECTIONS]
    cols = max(1, min(3, len(shown)))
    rows = max(1, -(-len(shown) // cols))
    fig = plt.figure(figsize=(5 * cols, 4.6 * rows + 2.6))
    grid = fig.add_gridspec(rows + 1, cols, height_ratios=[*([4.6] * rows), 2.6])
    lo, hi = p.min(0), p.max(0)
    size = max(float(np.max(hi - lo)), 0.2)
    t0 = tab.column("t_ns")[0].as_py()
    t = (tab.column("t_ns")[frame].as_py() - t0) * 1e-9
    for i, (s, j, d, parts) in enumerate(shown):
        ax = fig.add_subplot(grid[i // cols, i % cols], projection="3d")
        _draw_robot(ax, model, p)
        fmax = max([np.linalg.norm(f) for _, f, _ in parts] + [1e-9])
        scale = 0.25 * size / fmax
        pts, arrows = [p], []
        for c, fw, m in parts:
            ax.scatter(*c, color=_mpl(NULLSPACE_RGB), s=20, depthshade=False)
            ax.quiver(*c, *(fw * scale), color=_mpl(NULLSPACE_RGB), lw=2.2, label="force")
            if m is not None and np.linalg.norm(m) > 1e-9:
                ax.quiver(*c, *(m * scale), color="tab:green", lw=1.5, linestyle=":",
                          label="moment")  # fmt: skip
            pts += [c[None], (c + fw * scale)[None]]
            arrows.append(fw)
        _fit_view(ax, pts, arrows)
        ax.set_title(f"{s}: direction {j + 1} of {d}", fontsize=10)
    if not shown:
        ax = fig.add_subplot(grid[0, 0], projection="3d")
        _draw_robot(ax, model, p)
        _fit_view(ax, [p], [])
        ax.set_title("every sensor sees every unknown here (nullity 0)", fontsize=10)
    # the basis as a table: components of each direction by unknown
    tab_ax = fig.add_subplot(grid[rows, :])
    if shown:
        order = [lab for s in sensors for lab in labels[s]]
        names = sorted({lab for s, _, _, _ in shown for lab in labels[s]}, key=order.index)
        M = np.zeros((len(shown), len(names)))
        for i, (s, j, _, _) in enumerate(shown):
            for r, lab in enumerate(labels[s]):
                M[i, names.index(lab)] = bases[s][r, j]
        im = tab_ax.imshow(M, cmap="RdBu_r", vmin=-1, vmax=1, aspect="auto")
        small = 7 if M.size <= 120 else 5
        for (i, j), v in np.ndenumerate(M):  # each cell shows its value
            tab_ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=small,
                        color="w" if abs(v) > 0.6 else "k")  # fmt: skip
        tab_ax.set_xticks(range(len(names)), names, rotation=60, ha="right", fontsize=7)
        tab_ax.set_yticks(range(len(shown)), [f"{s} #{j + 1}" for s, j, _, _ in shown],
                          fontsize=8)  # fmt: skip
        fig.colorbar(im, ax=tab_ax, fraction=0.02, label="component (unit vector, link frames)")
    else:
        tab_ax.axis("off")
    more = f" (first {MAX_DIRECTIONS} of {len(dirs)})" if len(dirs) > len(shown) else ""
    title = (
        f"Unobservable directions at t = {t:.2f} s (row {frame}){more}: contact forces the"
        " sensors cannot tell apart (adding any multiple changes no reading); world frame,"
        " each direction's largest force drawn at 25 % of the robot's size"
    )
    fig.suptitle(textwrap.fill(title, 14 * 5 * cols), fontsize=9)
    handles, labs = [], []
    for ax in fig.axes:
        h, lab = ax.get_legend_handles_labels()
        handles += h
        labs += lab
    uniq = dict(zip(labs, handles, strict=True))
    if uniq:
        fig.legend(uniq.values(), uniq.keys(), loc="upper right", bbox_to_anchor=(1, 0.9),
                   fontsize=8)  # fmt: skip
    fig.tight_layout(rect=(0, 0, 1, 0.9))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
