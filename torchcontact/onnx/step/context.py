"""What every stage of the single-frame graph reads: a small, fixed context value."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from torchcontact.estimation.layout import EstimationModel
from torchcontact.onnx.builder import GraphBuilder
from torchcontact.onnx.format import StepLayout

__all__ = ["Flags", "StepContext"]


@dataclass(frozen=True)
class Flags:
    """Which optional inputs a graph has.

    Attributes:
        moving_base: inputs ``omega, domega, proper_acc`` instead of a fixed base.
        torque_rows: inputs ``tau_measured, tau_mask``: measured torques add equations.
        covariance: input ``ft_cov`` and output ``covariance``.
    """

    moving_base: bool = False
    torque_rows: bool = False
    covariance: bool = False

    def as_tuple(self) -> tuple[bool, bool, bool]:
        """``(moving_base, torque_rows, covariance)``, the program's flags."""
        return self.moving_base, self.torque_rows, self.covariance


@dataclass(frozen=True, eq=False)
class StepContext:
    """The constants of one single-frame graph; stages are functions of it.

    Attributes:
        em: the layout, pruned to the bodies the graph needs
            (:meth:`~torchcontact.estimation.EstimationModel.prune`).
        full: the layout before pruning (its body indices are the model's).
        keep: the model's body index of each pruned body.
        coords: the joint coordinates whose torques the graph outputs.
        flags: the optional inputs.
        gb: the graph being built.
        lay: the packed input's layout.
        extra: the extra columns chained corrections read, in order.
        online: per sensor its :class:`~torchcontact.online.state.SensorLayout` when the graph
            has the online inputs and outputs (:mod:`~torchcontact.onnx.step.online`), else
            empty.
        noise: per sensor (region) 6 standard deviations ``[N; N m]`` the solve is weighted by
            (:mod:`~torchcontact.onnx.step.solve`), or None: the unweighted ``pinv(A) b``.
    """

    em: EstimationModel
    full: EstimationModel
    keep: tuple[int, ...]
    coords: tuple[int, ...]
    flags: Flags
    gb: GraphBuilder
    lay: StepLayout = field(default_factory=StepLayout)
    extra: tuple[str, ...] = ()
    online: tuple = ()
    noise: tuple[tuple[float, ...], ...] | None = None

    @property
    def nb(self) -> int:
        """Bodies of the pruned tree."""
        return len(self.em.tree.bodies)

    @property
    def nv(self) -> int:
        """Joint coordinates."""
        return self.em.tree.nv

    @property
    def S(self) -> int:  # noqa: N802 - the paper's symbol
        """Sensors (regions)."""
        return len(self.em.regions)

    @property
    def K(self) -> int:  # noqa: N802
        """Contact slots."""
        return len(self.em.slots)

    @property
    def kinds(self) -> tuple[str, ...]:
        """Slot kinds."""
        return self.em.kinds

    @property
    def dtype(self) -> np.dtype:
        """The graph's float dtype."""
        return self.gb.dtype

    @cached_property
    def cut(self) -> np.ndarray:
        """:meth:`EstimationModel.cut_matrix` of the pruned tree, ``(nb, nb)``."""
        return self.em.cut_matrix()

    @cached_property
    def slot_bodies(self) -> np.ndarray:
        """``B[j, k] = 1`` when slot ``k`` lies on body ``j``, ``(nb, K)``."""
        B = np.zeros((self.nb, self.K))
        for k, s in enumerate(self.em.slots):
            B[s.body, k] = 1.0
        return B

    def whitening(self, r: int, R: int) -> np.ndarray | None:
        """``(R,)`` ``1 / sigma`` of region ``r``'s rows (torque rows: 1), None: unweighted."""
        if self.noise is None:
            return None
        w = np.ones(R)
        w[:6] = 1.0 / np.sqrt(np.square(np.asarray(self.noise[r], dtype=np.float64)))
        return w

    def depths(self) -> list[int]:
        """Depth of every body (the root 0)."""
        d = [0] * self.nb
        for i, b in enumerate(self.em.tree.bodies[1:], start=1):
            d[i] = d[b.parent] + 1
        return d

    def static_pose(self, body: int) -> tuple[np.ndarray, np.ndarray] | None:
        """``T_root_body`` (internal frames) when no joint between the root and ``body`` moves."""
        R, p = np.eye(3), np.zeros(3)
        chain = []
        i = body
        while i > 0:
            b = self.em.tree.bodies[i]
            if b.kind != "fixed":
                return None
            chain.append(b)
            i = b.parent
        for b in reversed(chain):
            p = R @ np.array(b.p, dtype=float) + p
            R = R @ np.array(b.C, dtype=float)
        return R, p

    def all_static(self, bodies: Sequence[int]) -> bool:
        """Whether every body of ``bodies`` has a :meth:`static_pose`."""
        return all(self.static_pose(b) is not None for b in bodies)
