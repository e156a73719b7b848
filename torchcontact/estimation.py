"""Contact wrench estimation from F/T sensors and tactile contact locations, batched.

Del Prete, Natale, Nori, Metta, *Contact Force Estimations Using Tactile Sensors and Force/Torque
Sensors*, HRI 2012, Sec. 2, generalised to several sensors, joint torque sensors and moving bases.

**Regions.** The chosen F/T sensors cut the kinematic tree. The *region* of a sensor is its
subtree (the far side of its joint) minus the subtrees of sensors nested inside it; the bodies on
the root side of every sensor form the root region, where no contact can be estimated (its link to
the world is unmeasured). A contact belongs to the region of its link's body.

**Equations (Sec. 2.1-2.2).** For region ``s`` with reading ``W_s`` (the wrench its sensor's parent
side exerts on the region, in the sensor frame) and nested sensors ``s'`` bordering it, Newton-Euler
of the region's bodies gives, in the sensor frame about its origin::

    sum_k X_k w_k = sum_{i in s} (I_i a_i + v_i x* I_i v_i) - W_s + sum_{s'} W_s' - sum known_k
           A x    =                               b

where ``w_k = [force; moment about the contact point]`` in the contact link's frame and ``X_k``
maps it to the sensor frame (the paper's Eq. 3). A measured joint torque of a joint ``j`` inside
the region adds one row ``S_j^T (sum of the same terms over the part of the region beyond j)``
(the paper's future work).

**Unknowns.** Each contact slot contributes ``w_k = P_k x_k`` with an orthogonal projector ``P_k``:
``wrench`` I6 (6 unknowns), ``force`` diag(1,1,1,0,0,0) (3), ``force_dir`` ``[d d^T, 0; 0, 0]`` for
the unit direction ``d`` (1), ``known`` and inactive 0. Then ``A A^T = sum_k X_k P_k X_k^T`` is a
small ``(6+m) x (6+m)`` matrix whatever the number of contacts, and the pseudo-inverse solution
``x* = pinv(A) b`` (least squares, minimum norm when rank-deficient) is
``w_k = P_k X_k^T (A A^T)^+ b``. ``(A A^T)^+`` comes from a symmetric eigendecomposition whose
eigenvalues also give the rank.

**Rank tolerance.** ``rank`` counts eigenvalues of ``A A^T`` above ``rank_rtol * lambda_max`` with
``rank_rtol = rows * eps(dtype)`` by default, i.e. singular values of ``A`` above
``sqrt(rank_rtol) * sigma_max`` (about 3.7e-8 sigma_max in float64 for 6 rows). Directions below
the tolerance are treated as unobservable: they get no share of the solution.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchcontact import _jacobi
from torchcontact import dynamics as _dyn
from torchcontact._internal import check_input, flatten_batch
from torchcontact.contacts import KINDS, Contacts
from torchcontact.dynamics import BaseMotion
from torchcontact.model import FTSensor, RobotModel
from torchcontact.status import STATUS, status_messages

__all__ = ["KINDS", "STATUS", "ContactEstimate", "ContactEstimator", "Contacts", "status_messages"]


class ContactEstimate(NamedTuple):
    """Result of :meth:`ContactEstimator.estimate`; ``*B`` is the input batch shape.

    Attributes:
        force: ``(*B, K, 3)`` contact forces in each contact's link frame, N (0 where inactive;
            the given force for ``known`` slots).
        moment: ``(*B, K, 3)`` contact moments about the contact point, link frame, N m.
        rank: sensor -> ``(*B,)`` int64 rank of A.
        unknowns: sensor -> ``(*B,)`` int64 number of unknowns.
        residual: sensor -> ``(*B,)`` ``|A x* - b|`` (N and N m mixed, as the paper's b).
        identifiable: sensor -> ``(*B,)`` bool, ``rank == unknowns`` (every unknown determined).
        joint_torques: ``(*B, nv)`` joint torques in ``model.joint_names`` order, N m or N.
        status: ``(*B,)`` int64, 0 if ok, else bits of :data:`STATUS`; outputs of such frames
            are NaN.
        covariance: ``(*B, K, 6, 6)`` covariance of each slot's ``[force; moment]`` from the F/T
            noise covariance, or None when not asked for.
    """

    force: Tensor
    moment: Tensor
    rank: dict[str, Tensor]
    unknowns: dict[str, Tensor]
    residual: dict[str, Tensor]
    identifiable: dict[str, Tensor]
    joint_torques: Tensor
    status: Tensor
    covariance: Tensor | None = None


class ContactEstimator:
    """Estimate contact wrenches and joint torques from F/T readings, batched over frames.

    Args:
        model: the robot; its dtype and device are those of the computation.
        sensors: names of F/T sensors of ``model.ft_sensors`` to use (default: all of them).
            Sensors not used do not cut the tree.
        solver: eigensolver of the Gram matrix ``A A^T``: ``"eigh"`` (``torch.linalg.eigh``,
            LAPACK/cuSOLVER) or ``"jacobi"`` (a fixed number of cyclic Jacobi sweeps in elementwise
            ops, :mod:`torchcontact._jacobi`; exports to ONNX, agrees with ``eigh`` to rounding).
        jacobi_sweeps: sweeps of the ``"jacobi"`` solver (default
            :data:`torchcontact._jacobi.DEFAULT_SWEEPS`; fewer suffice in float32, see there).

    Raises:
        ValueError: an unknown sensor name or solver, or ``jacobi_sweeps < 1``.

    Example:
        >>> import torch, torchcontact as tc
        >>> model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
        >>> est = tc.ContactEstimator(model)  # the arm's base F/T sensor "base_ft"
        >>> q = torch.zeros(2, model.nv, dtype=torch.float64)  # (B, nv), at rest
        >>> pos = torch.zeros(2, 1, 3, dtype=torch.float64)  # (B, K, 3) contact at the patch origin
        >>> push = torch.tensor([0, 0, -10.0, 0, 0, 0], dtype=torch.float64).expand(2, 1, 6)
        >>> ft = est.predict_ft(q, q, q, tc.Contacts(["hand_skin"], ["known"], pos, wrenches=push))
        >>> r = est.estimate(q, q, q, ft, tc.Contacts(["hand_skin"], ["force"], pos))
        >>> r.force.round(decimals=6), r.rank["base_ft"]
        (tensor([[[  0.,   0., -10.]],
        <BLANKLINE>
                [[  0.,   0., -10.]]], dtype=torch.float64), tensor([3, 3]))
    """

    def __init__(
        self,
        model: RobotModel,
        sensors: Sequence[str] | None = None,
        solver: str = "eigh",
        jacobi_sweeps: int | None = None,
    ) -> None:
        if solver not in ("eigh", "jacobi"):
            raise ValueError(f"unknown solver {solver!r}; expected 'eigh' or 'jacobi'")
        self.solver = solver
        sweeps = _jacobi.DEFAULT_SWEEPS if jacobi_sweeps is None else int(jacobi_sweeps)
        if sweeps < 1:
            raise ValueError(f"jacobi_sweeps must be >= 1, got {jacobi_sweeps}")
        self.jacobi_sweeps = sweeps
        names = list(model.ft_sensors) if sensors is None else list(sensors)
        unknown = [s for s in names if s not in model.ft_sensors]
        if unknown:
            raise ValueError(
                f"unknown F/T sensors {unknown}; the model has {list(model.ft_sensors)}"
                " (add one with model.with_ft_sensor)"
            )
        if not names:
            raise ValueError(f"{model.name} has no F/T sensor to estimate contacts from")
        self.model = model
        self.sensors: tuple[FTSensor, ...] = tuple(model.ft_sensors[s] for s in names)
        self.sensor_names = tuple(names)
        nb, S = model.nb, len(names)
        # region of each body: index of the nearest chosen sensor towards the root, -1 for root
        child_of_sensor = {s.child_body: i for i, s in enumerate(self.sensors)}
        region = [-1] * nb
        for b in range(nb):  # breadth-first order: the parent's region is known
            if b in child_of_sensor:
                region[b] = child_of_sensor[b]
            elif model.body_parent[b] >= 0:
                region[b] = region[model.body_parent[b]]
        self.region = tuple(region)
        # the region a sensor's parent side lies in (-1: root region)
        self.sensor_parent_region = tuple(region[s.parent_body] for s in self.sensors)
        # sensors processed deepest first in the backward pass
        depth = {b: d for d, (s, e) in enumerate(model.levels) for b in range(s, e)}
        self._deep_first = sorted(range(S), key=lambda i: -depth[self.sensors[i].child_body])
        anc = np.zeros((S, nb))  # body is an ancestor-or-self of sensor i's child body
        for i, s in enumerate(self.sensors):
            b = s.child_body
            while b >= 0:
                anc[i, b] = 1.0
                b = model.body_parent[b]
        region_mask = np.zeros((S, nb))
        for b, r in enumerate(region):
            if r >= 0:
                region_mask[r, b] = 1.0
        # nested[i, j] = +1 when sensor j borders region i from inside
        nested = np.zeros((S, S))
        for j, r in enumerate(self.sensor_parent_region):
            if r >= 0:
                nested[r, j] = 1.0
        sign = [1.0 if s.measure_direction == "parent_to_child" else -1.0 for s in self.sensors]
        # joints with a possible torque measurement, per region: moving joints of region bodies
        self._region_joints: list[list[int]] = [[] for _ in range(S)]
        for b in range(nb):
            if region[b] >= 0 and (model.is_revolute[b] or model.is_prismatic[b]):
                self._region_joints[region[b]].append(b)
        self._m = max((len(j) for j in self._region_joints), default=0)
        # within-region subtree masks of each region joint: desc[r, row, body]
        m = self._m
        desc = np.zeros((S, m, nb))
        nested_desc = np.zeros((S, m, S))
        for r, joints in enumerate(self._region_joints):
            for row, jb in enumerate(joints):
                for i in model.subtree(jb):
                    if region[i] == r:
                        desc[r, row, i] = 1.0
                for j, s in enumerate(self.sensors):
                    if nested[r, j] and s.child_body in model.subtree(jb):
                        nested_desc[r, row, j] = 1.0

        def t(x):
            return torch.as_tensor(np.asarray(x), dtype=model.dtype, device=model.device)

        self._anc, self._region_mask, self._nested = t(anc), t(region_mask), t(nested)
        self._sign = t(sign)
        self._desc, self._nested_desc = t(desc), t(nested_desc)
        self._R_cs = t(np.stack([s.R_child_sensor for s in self.sensors]))
        self._p_cs = t(np.stack([s.p_child_sensor for s in self.sensors]))
        self._child = torch.tensor([s.child_body for s in self.sensors], device=model.device)
        self._region_joint_index = torch.tensor(
            [r[i] if i < len(r) else 0 for r in self._region_joints for i in range(m)],
            device=model.device,
            dtype=torch.long,
        ).reshape(S, m)
        self._region_joint_valid = t(
            [[1.0 if i < len(r) else 0.0 for i in range(m)] for r in self._region_joints]
        ).reshape(S, m)
        # joint coordinate of each region joint (for tau_measured): argmax of q_to_body column
        qb = model.q_to_body.abs().argmax(0)
        self._region_joint_coord = qb[self._region_joint_index]
        self._layout_cache: dict = {}

    # ------------------------------------------------------------------ contact layout
    def _layout(self, contacts: Contacts):
        key = (contacts.links, contacts.kinds)
        if key in self._layout_cache:
            return self._layout_cache[key]
        model = self.model
        bodies, R_bl, p_bl, regions = [], [], [], []
        for link in contacts.links:
            try:
                fr = model.frame(link)
            except KeyError as e:
                raise ValueError(f"contact on unknown link: {e.args[0]}") from None
            r = self.region[fr.body]
            if r < 0:
                raise ValueError(
                    f"contact on link {link!r} lies outside every F/T sensor's subtree"
                    f" (sensors {list(self.sensor_names)}): nothing measures it"
                )
            bodies.append(fr.body)
            regions.append(r)
            R_bl.append(fr.R_body_frame)
            p_bl.append(fr.p_body_frame)

        def t(x):
            return torch.as_tensor(np.asarray(x), dtype=model.dtype, device=model.device)

        K = contacts.K
        lay = {
            "body": torch.tensor(bodies, device=model.device, dtype=torch.long),
            "region": torch.tensor(regions, device=model.device, dtype=torch.long),
            "region_onehot": t(
                np.eye(len(self.sensors))[regions].T if K else np.zeros((len(self.sensors), 0))
            ),
            "R_bl": t(np.stack(R_bl) if K else np.zeros((0, 3, 3))),
            "p_bl": t(np.stack(p_bl) if K else np.zeros((0, 3))),
            "is": {k: t([1.0 if kind == k else 0.0 for kind in contacts.kinds]) for k in KINDS},
            "n_unknowns": t([KINDS[k] for k in contacts.kinds]),
            # regions holding at least one slot: the only ones with a system to solve
            "solved": torch.tensor(sorted(set(regions)), device=model.device, dtype=torch.long),
            # in-region-subtree mask of each region joint for each slot: (S, m, K)
            "slot_desc": self._desc[:, :, bodies] if K else self._desc[:, :, :0],
        }
        self._layout_cache[key] = lay
        return lay

    # ------------------------------------------------------------------ public API
    def estimate(
        self,
        q: Tensor,
        qd: Tensor,
        qdd: Tensor,
        ft: Mapping[str, Tensor],
        contacts: Contacts,
        *,
        gravity: Tensor | tuple[float, float, float] = (0.0, 0.0, -9.81),
        base: BaseMotion | None = None,
        tau_measured: Tensor | None = None,
        tau_mask: Tensor | None = None,
        ft_covariance: Mapping[str, Tensor] | None = None,
        rank_rtol: float | None = None,
        chunk_size: int | None = 8192,
    ) -> ContactEstimate:
        """Estimate the contacts of every frame (Del Prete et al. 2012, Sec. 2).

        Args:
            q: ``(*B, nv)`` joint positions, rad or m, ``model.joint_names`` order.
            qd: ``(*B, nv)`` joint velocities.
            qdd: ``(*B, nv)`` joint accelerations.
            ft: sensor name -> ``(*B, 6)`` reading ``[force (N); moment (N m)]`` in the sensor's
                declared frame and measure direction.
            contacts: the contact slots (:class:`Contacts`) with ``(*B, K, ...)`` data.
            gravity: ``(3,)`` or ``(*B, 3)`` gravity in the root frame, m/s^2 (fixed base).
            base: IMU measurement of a moving base (:class:`BaseMotion`).
            tau_measured: ``(*B, nv)`` measured joint torques (joint torque sensors), N m or N;
                each measured joint inside a sensor region adds an equation.
            tau_mask: ``(nv,)`` or ``(*B, nv)`` bool, which joints have a torque measurement
                (default: all finite entries of ``tau_measured``).
            ft_covariance: sensor name -> ``(6, 6)`` or ``(*B, 6, 6)`` covariance of its reading
                noise; when given, ``covariance`` of the result is filled with the first-order
                propagation of each region's own sensor noise (noise of nested sensors and of
                measured joint torques is not included).
            rank_rtol: relative eigenvalue tolerance of ``A A^T`` for the rank (see module doc).
            chunk_size: frames processed at once (bounds memory and keeps data in cache); None
                for one go.

        Returns:
            :class:`ContactEstimate`.

        Raises:
            ValueError: wrong shapes/dtype/device, a missing sensor reading, a contact on an
                unknown link or outside every sensor's subtree. Non-finite values and zero-length
                directions do not raise: the frame gets a ``status`` and NaN outputs.
        """
        model, S = self.model, len(self.sensors)
        K = contacts.K
        nv, dtype = model.nv, model.dtype
        if chunk_size is not None and isinstance(q, Tensor) and q.dim() >= 1:
            n_frames = q.shape[:-1].numel()
            if n_frames > chunk_size:
                return self._estimate_chunked(
                    chunk_size, q, qd, qdd, ft, contacts, gravity=gravity, base=base,
                    tau_measured=tau_measured, tau_mask=tau_mask, ft_covariance=ft_covariance,
                    rank_rtol=rank_rtol,
                )  # fmt: skip
        # ---- validate shapes (values are checked per frame below)
        for name, x in (("q", q), ("qd", qd), ("qdd", qdd)):
            check_input(name, x, (nv,), model, f"(*B, {nv})", finite=False)
        batch = q.shape[:-1]
        if qd.shape[:-1] != batch or qdd.shape[:-1] != batch:
            raise ValueError("q, qd, qdd must share their batch shape")
        n = math.prod(batch)  # (not batch.numel(): keeps a symbolic batch size symbolic in export)
        missing = [s for s in self.sensor_names if s not in ft]
        if missing:
            raise ValueError(f"ft is missing readings of sensors {missing} (keys: {list(ft)})")
        extra = [s for s in ft if s not in self.sensor_names]
        if extra:
            raise ValueError(f"ft has readings of unknown or unused sensors {extra}")

        def per_frame(name: str, x: Tensor | None, trailing: tuple[int, ...]) -> Tensor | None:
            if x is None:
                return None
            shape = f"(*B, {', '.join(map(str, trailing))})"
            check_input(name, x, trailing, model, shape, finite=False)
            if x.shape[: x.dim() - len(trailing)] != batch:
                raise ValueError(
                    f"{name} must be {shape} with B={tuple(batch)}, got {tuple(x.shape)}"
                )
            return flatten_batch(x, batch, len(trailing))

        readings = torch.stack([per_frame(f"ft[{s!r}]", ft[s], (6,)) for s in self.sensor_names], 1)
        pos = per_frame("contacts.positions", contacts.positions, (K, 3))
        need_dir = "force_dir" in contacts.kinds
        need_wr = "known" in contacts.kinds
        if need_dir and contacts.directions is None:
            raise ValueError("contacts.directions is required for force_dir slots")
        if need_wr and contacts.wrenches is None:
            raise ValueError("contacts.wrenches is required for known slots")
        dirs = per_frame("contacts.directions", contacts.directions, (K, 3))
        wr = per_frame("contacts.wrenches", contacts.wrenches, (K, 6))
        if contacts.active is not None:
            act = contacts.active
            if not isinstance(act, Tensor) or act.shape != (*batch, K):
                raise ValueError(
                    f"contacts.active must be a (*B, {K}) tensor, got {getattr(act, 'shape', act)}"
                )
            active = act.reshape(n, K).to(dtype=dtype, device=model.device)
        else:
            active = pos.new_ones(n, K)
        qf, qdf, qddf = (flatten_batch(x, batch, 1) for x in (q, qd, qdd))
        status = torch.zeros(n, dtype=torch.long, device=model.device)

        def flag(bad: Tensor, bit: int) -> None:
            nonlocal status
            # each bit is flagged once, so + is |; (exports: ONNX has no integer bitwise or)
            status = status + bad.to(torch.long) * bit

        def finite_rows(x: Tensor) -> Tensor:
            return torch.isfinite(x).reshape(n, -1).all(-1)

        flag(~finite_rows(readings), 1)
        joint_ok = finite_rows(torch.cat((qf, qdf, qddf), -1))
        if base is not None:
            base_t = [per_frame(f"base.{k}", getattr(base, k), (3,)) for k in BaseMotion._fields]
            joint_ok = joint_ok & finite_rows(torch.cat(base_t, -1))
        flag(~joint_ok, 2)
        act_b = active > 0
        lay = self._layout(contacts)
        # a field counts only where an active slot's kind uses it (directions: force_dir,
        # wrenches: known); NaN elsewhere, e.g. a null direction of a pure force, is ignored
        bad_c = (~torch.isfinite(pos).all(-1) & act_b).any(-1)
        for x, kind in ((dirs, "force_dir"), (wr, "known")):
            if x is not None:
                uses = act_b & (lay["is"][kind] > 0)
                bad_c = bad_c | (~torch.isfinite(x).all(-1) & uses).any(-1)
        flag(bad_c, 4)
        if dirs is not None:
            norm = dirs.norm(dim=-1)
            zero_dir = (norm <= 0) & act_b & (lay["is"]["force_dir"] > 0)
            flag(zero_dir.any(-1), 8)
        if tau_measured is not None:
            tau_m = per_frame("tau_measured", tau_measured, (nv,))
            if tau_mask is None:
                mask = torch.isfinite(tau_m)
            else:
                mask = tau_mask.to(torch.bool).expand(*batch, nv).reshape(n, nv)
                flag((~torch.isfinite(tau_m) & mask).any(-1), 16)
        ok = status == 0

        # ---- sanitise bad frames so they cannot poison the batch; their outputs become NaN
        def clean(x: Tensor | None) -> Tensor | None:
            if x is None:
                return None
            keep = ok.reshape(n, *([1] * (x.dim() - 1)))
            return torch.where(keep & torch.isfinite(x), x, torch.zeros_like(x))

        qf, qdf, qddf, readings, pos, dirs, wr = map(
            clean, (qf, qdf, qddf, readings, pos, dirs, wr)
        )
        if dirs is not None:
            dn = dirs.norm(dim=-1, keepdim=True)
            dirs = dirs / torch.where(dn > 0, dn, torch.ones_like(dn))
        if base is None:
            base_bl = _dyn._gravity_base(model, gravity, batch, qf)
        else:
            base_bl = tuple(clean(x).T for x in base_t)
        meas = None
        if tau_measured is not None:
            meas = (clean(tau_m), mask & ok.unsqueeze(-1))
        cov_in = None
        if ft_covariance is not None:
            cov_in = torch.zeros(n, S, 6, 6, dtype=dtype, device=model.device)
            for i, s in enumerate(self.sensor_names):
                if s in ft_covariance:
                    c = ft_covariance[s]
                    check_input(f"ft_covariance[{s!r}]", c, (6, 6), model, "(6, 6) or (*B, 6, 6)")
                    cov_in[:, i] = c.expand(*batch, 6, 6).reshape(n, 6, 6)

        out = self._estimate_bl(
            qf.T,
            qdf.T,
            qddf.T,
            base_bl,
            readings,
            lay,
            pos,
            dirs,
            wr,
            active,
            meas,
            cov_in,
            rank_rtol,
        )
        force, moment, rank, unknowns, residual, tau, cov = out
        nan = torch.tensor(float("nan"), dtype=dtype, device=model.device)
        bad = ~ok

        def fin(x: Tensor, trailing: tuple[int, ...], fill=nan) -> Tensor:
            x = torch.where(bad.reshape(n, *([1] * len(trailing))), fill, x)
            return x.reshape((*batch, *trailing))

        ident = rank == unknowns
        return ContactEstimate(
            force=fin(force, (K, 3)),
            moment=fin(moment, (K, 3)),
            rank={s: rank[:, i].reshape(batch) for i, s in enumerate(self.sensor_names)},
            unknowns={s: unknowns[:, i].reshape(batch) for i, s in enumerate(self.sensor_names)},
            residual={s: fin(residual[:, i], ()) for i, s in enumerate(self.sensor_names)},
            identifiable={s: ident[:, i].reshape(batch) for i, s in enumerate(self.sensor_names)},
            joint_torques=fin(tau, (nv,)),
            status=status.reshape(batch),
            covariance=None if cov is None else fin(cov, (K, 6, 6)),
        )

    def _estimate_chunked(self, chunk_size, q, qd, qdd, ft, contacts, **kw) -> ContactEstimate:
        """:meth:`estimate` over chunks of the flattened batch, results concatenated."""
        batch = q.shape[:-1]
        n = batch.numel()

        def flat(x, feat):
            if not isinstance(x, Tensor) or x.dim() < feat or x.shape[: x.dim() - feat] != batch:
                return x  # per-frame shape errors are reported by the un-chunked call
            return x.reshape(n, *x.shape[x.dim() - feat :])

        def cut(x, feat, sl):
            x = flat(x, feat)
            if isinstance(x, Tensor) and x.dim() > feat and x.shape[0] == n:
                return x[sl]
            return x

        outs = []
        for s in range(0, n, chunk_size):
            sl = slice(s, min(n, s + chunk_size))
            c = Contacts(
                contacts.links, contacts.kinds, cut(contacts.positions, 2, sl),
                None if contacts.directions is None else cut(contacts.directions, 2, sl),
                None if contacts.wrenches is None else cut(contacts.wrenches, 2, sl),
                None if contacts.active is None else cut(contacts.active, 1, sl),
            )  # fmt: skip
            extra = dict(kw)
            for key, feat in (("tau_measured", 1), ("tau_mask", 1)):
                if extra.get(key) is not None:
                    extra[key] = cut(extra[key], feat, sl)
            if isinstance(extra.get("gravity"), Tensor):
                extra["gravity"] = cut(extra["gravity"], 1, sl)
            if extra.get("base") is not None:
                extra["base"] = BaseMotion(*(cut(x, 1, sl) for x in extra["base"]))
            if extra.get("ft_covariance") is not None:
                extra["ft_covariance"] = {
                    k: cut(v, 2, sl) for k, v in extra["ft_covariance"].items()
                }
            outs.append(
                self.estimate(
                    cut(q, 1, sl), cut(qd, 1, sl), cut(qdd, 1, sl),
                    {k: cut(v, 1, sl) for k, v in ft.items()}, c, chunk_size=None, **extra,
                )
            )  # fmt: skip

        def join(xs):
            if isinstance(xs[0], dict):
                return {k: join([x[k] for x in xs]) for k in xs[0]}
            if xs[0] is None:
                return None
            y = torch.cat(xs)
            return y.reshape(*batch, *y.shape[1:])

        return ContactEstimate(*(join([o[i] for o in outs]) for i in range(len(outs[0]))))

    def predict_ft(
        self,
        q: Tensor,
        qd: Tensor,
        qdd: Tensor,
        contacts: Contacts,
        *,
        gravity: Tensor | tuple[float, float, float] = (0.0, 0.0, -9.81),
        base: BaseMotion | None = None,
    ) -> dict[str, Tensor]:
        """F/T readings the model predicts for known contact wrenches (forward model, simulation).

        Every active slot's ``contacts.wrenches`` is applied, whatever its kind; with no active
        slot this is the contact-free prediction that calibration and residual learning use.

        Args:
            q: ``(*B, nv)`` joint positions; ``qd``, ``qdd`` likewise.
            qd: ``(*B, nv)`` joint velocities.
            qdd: ``(*B, nv)`` joint accelerations.
            contacts: slots with ``wrenches`` ``(*B, K, 6)`` (link frame, moment about the point).
            gravity: ``(3,)`` or ``(*B, 3)`` gravity in the root frame, m/s^2.
            base: IMU measurement of a moving base.

        Returns:
            sensor name -> ``(*B, 6)`` reading ``[force; moment]`` in its frame and direction.
        """
        model, K = self.model, contacts.K
        batch, (qb, qdb, qddb), base_bl = _dyn._prepare(model, q, qd, qdd, gravity, base)
        n = batch.numel()
        lay = self._layout(contacts)
        if K and contacts.wrenches is None:
            raise ValueError("predict_ft needs contacts.wrenches")
        pos = flatten_batch(contacts.positions, batch, 2) if K else qb.new_zeros(n, 0, 3)
        wr = flatten_batch(contacts.wrenches, batch, 2) if K else qb.new_zeros(n, 0, 6)
        act = (
            contacts.active.reshape(n, K).to(model.dtype)
            if contacts.active is not None
            else wr.new_ones(n, K)
        )
        fp = _dyn._forward_bl(model, qb, qdb, qddb, *base_bl)
        f = _dyn._body_wrenches_bl(model, fp)
        W_root = self._contact_wrenches_root(
            fp, lay, pos.permute(1, 2, 0), (wr * act.unsqueeze(-1)).permute(1, 2, 0)
        )
        f = f - self._scatter_bodies(W_root, lay)
        F = _dyn.subtree_sum(model, f)
        W_pc = F.index_select(0, self._child)  # wrench the parent side exerts on each subtree
        reading = self._root_to_sensor(fp, W_pc) * self._sign.reshape(-1, 1, 1)
        return {s: reading[i].T.reshape(*batch, 6) for i, s in enumerate(self.sensor_names)}

    # ------------------------------------------------------------------ internals (batch-last)
    def _sensor_pose(self, fp):
        """``T_root_sensor`` of every chosen sensor: ``R (S, 3, 3, N)``, ``p (S, 3, N)``."""
        Rc = fp.R.index_select(0, self._child)
        pc = fp.p.index_select(0, self._child)
        R = (Rc.unsqueeze(3) * self._R_cs.unsqueeze(1).unsqueeze(-1)).sum(2)
        p = pc + _dyn._mv_bl(Rc, self._p_cs.unsqueeze(-1))
        return R, p

    def _root_to_sensor(self, fp, W: Tensor) -> Tensor:
        """Wrenches ``(S, 6, N)`` at the root origin to each sensor's frame about its origin."""
        R, p = self._sensor_pose(fp)
        f, m = W[:, :3], W[:, 3:]
        Rt = R.transpose(1, 2)
        return torch.cat((_dyn._mv_bl(Rt, f), _dyn._mv_bl(Rt, m - _dyn._cross_bl(p, f))), 1)

    def _sensor_to_root(self, fp, W: Tensor) -> Tensor:
        R, p = self._sensor_pose(fp)
        f = _dyn._mv_bl(R, W[:, :3])
        return torch.cat((f, _dyn._mv_bl(R, W[:, 3:]) + _dyn._cross_bl(p, f)), 1)

    def _contact_frames(self, fp, lay, pos: Tensor):
        """Contact link rotations ``(K, 3, 3, N)`` and contact points ``(K, 3, N)`` in the root."""
        Rb = fp.R.index_select(0, lay["body"])
        pb = fp.p.index_select(0, lay["body"])
        R = (Rb.unsqueeze(3) * lay["R_bl"].unsqueeze(1).unsqueeze(-1)).sum(2)
        c = pb + _dyn._mv_bl(
            Rb, lay["p_bl"].unsqueeze(-1) + _dyn._mv_bl(lay["R_bl"].unsqueeze(-1), pos)
        )
        return R, c

    def _contact_wrenches_root(self, fp, lay, pos: Tensor, w: Tensor) -> Tensor:
        """Contact wrenches ``(K, 6, N)`` (link frame, about the point) to the root origin."""
        R, c = self._contact_frames(fp, lay, pos)
        f = _dyn._mv_bl(R, w[:, :3])
        return torch.cat((f, _dyn._mv_bl(R, w[:, 3:]) + _dyn._cross_bl(c, f)), 1)

    def _scatter_bodies(self, W: Tensor, lay) -> Tensor:
        """Sum per-slot wrenches ``(K, 6, N)`` onto their bodies: ``(nb, 6, N)``."""
        out = W.new_zeros(self.model.nb, *W.shape[1:])
        return out.index_add(0, lay["body"], W)

    def _estimate_bl(
        self, q, qd, qdd, base_bl, readings, lay, pos, dirs, wr, active, meas, cov_in, rank_rtol
    ):
        model, S = self.model, len(self.sensors)
        n = q.shape[-1]
        K = pos.shape[1]
        dtype = q.dtype
        fp = _dyn._forward_bl(model, q, qd, qdd, *base_bl)
        f = _dyn._body_wrenches_bl(model, fp)  # (nb, 6, N) at the root origin
        # readings -> wrench each sensor's parent side exerts on its region, in the root frame
        W_meas = readings.permute(1, 2, 0) * self._sign.reshape(-1, 1, 1)  # (S, 6, N) sensor frame
        W_root = self._sensor_to_root(fp, W_meas)
        posb = pos.permute(1, 2, 0)  # (K, 3, N)
        act = active.T.unsqueeze(1)  # (1->K, 1, N)
        R_c, c_root = self._contact_frames(fp, lay, posb)
        # known contacts (applied, in the root frame)
        if wr is not None:
            wk = wr.permute(1, 2, 0) * act * lay["is"]["known"].reshape(-1, 1, 1)
            fk = _dyn._mv_bl(R_c, wk[:, :3])
            W_known = torch.cat((fk, _dyn._mv_bl(R_c, wk[:, 3:]) + _dyn._cross_bl(c_root, fk)), 1)
        else:
            wk, W_known = None, f.new_zeros(K, 6, n)
        f_known = f - self._scatter_bodies(W_known, lay)  # body wrenches net of known contacts
        # b in the root frame for every region: sum of region bodies - own reading + nested readings
        b_root = torch.einsum("sb,bkn->skn", self._region_mask, f_known)
        b_root = b_root - W_root + torch.einsum("sj,jkn->skn", self._nested, W_root)
        b6 = self._root_to_sensor(fp, b_root)  # (S, 6, N) in each sensor frame
        # X_k: contact wrench (link frame, about the point) -> its region's sensor frame
        Rs, ps = self._sensor_pose(fp)
        Rs_k, ps_k = Rs.index_select(0, lay["region"]), ps.index_select(0, lay["region"])
        R_sl = (Rs_k.transpose(1, 2).unsqueeze(3) * R_c.unsqueeze(1)).sum(2)  # (K, 3, 3, N)
        c_s = _dyn._mv_bl(Rs_k.transpose(1, 2), c_root - ps_k)  # contact point in sensor frame
        cxR = torch.stack([_dyn._cross_bl(c_s, R_sl[:, :, j]) for j in range(3)], 2)
        zero = torch.zeros_like(R_sl)
        X = torch.cat((torch.cat((R_sl, zero), 2), torch.cat((cxR, R_sl), 2)), 1)  # (K, 6, 6, N)
        # projector of each slot onto its unknowns
        is_ = lay["is"]
        eye3 = torch.eye(3, dtype=dtype, device=q.device)
        P_force = torch.zeros(K, 6, 6, 1, dtype=dtype, device=q.device)
        P_force[:, :3, :3] = eye3.unsqueeze(-1)
        eye6 = torch.eye(6, dtype=dtype, device=q.device).unsqueeze(-1)
        P = is_["wrench"].reshape(-1, 1, 1, 1) * eye6 + is_["force"].reshape(-1, 1, 1, 1) * P_force
        if dirs is not None:
            d = dirs.permute(1, 2, 0)  # (K, 3, N)
            ddT = d.unsqueeze(2) * d.unsqueeze(1)
            P = P + torch.nn.functional.pad(
                is_["force_dir"].reshape(-1, 1, 1, 1) * ddT, (0, 0, 0, 3, 0, 3)
            )
        P = P * act.unsqueeze(1)  # inactive slots: no unknowns
        # rows: 6 sensor rows, then the torque rows of measured joints inside the region
        m = self._m if meas is not None else 0
        if m:
            tau_m, mask = meas
            rows_joint = self._region_joint_index  # (S, m) body of each row
            S_rows = fp.S.index_select(0, rows_joint.reshape(-1)).reshape(S, m, 6, n)
            valid = self._region_joint_valid.unsqueeze(-1) * mask.T[self._region_joint_coord].to(
                dtype
            )
            # torque rows of slot k: S_j^T X_k_root, only for joints whose region subtree holds k
            Rk, ck = R_c, c_root
            # X_k_root^T S_j: coefficient on force R^T (s_lin + s_ang x c), on moment R^T s_ang
            Sj = S_rows[:, :, None].expand(S, m, K, 6, n)
            s_lin, s_ang = Sj[:, :, :, :3], Sj[:, :, :, 3:]
            cf = s_lin + _dyn._cross_bl(s_ang, ck.expand(S, m, K, 3, n))
            RkT = Rk.transpose(1, 2)
            t_f = _dyn._mv_bl(RkT, cf)
            t_n = _dyn._mv_bl(RkT, s_ang)
            sel = lay["slot_desc"].unsqueeze(-1).unsqueeze(-1) * valid.unsqueeze(2).unsqueeze(3)
            T = torch.cat((t_f, t_n), 3) * sel  # (S, m, K, 6, N)
            # b rows: S_j^T (sum over region subtree of j of f_known + nested readings) - tau_j
            Fj = torch.einsum("smb,bkn->smkn", self._desc, f_known)
            Fj = Fj + torch.einsum("smj,jkn->smkn", self._nested_desc, W_root)
            tau_rows = tau_m.T[self._region_joint_coord]  # (S, m, N)
            # mimic joints share a coordinate: their torque is measured on the leader only
            b_t = ((S_rows * Fj).sum(2) - tau_rows) * valid
        # assemble G = sum_k Y_k P_k Y_k^T per region, with Y_k = [X_k; T_k]
        onehot = lay["region_onehot"]  # (S, K)
        XP = (X.unsqueeze(3) * P.unsqueeze(1)).sum(2)  # (K, 6, 6, N): X_k P_k
        G6 = torch.einsum("sk,kijn,kljn->siln", onehot, XP, X)
        if m:
            Tk = T.permute(0, 2, 1, 3, 4)  # (S, K, m, 6, N)
            TP = (Tk.unsqueeze(4) * P.unsqueeze(0).unsqueeze(2)).sum(3)  # (S, K, m, 6, N)
            G_xt = torch.einsum("sk,kijn,skrjn->sirn", onehot, XP, Tk)  # (S, 6, m, N)
            G_tt = torch.einsum("skrjn,skqjn->srqn", TP, Tk)
            G = torch.cat((torch.cat((G6, G_xt), 2), torch.cat((G_xt.transpose(1, 2), G_tt), 2)), 1)
            b = torch.cat((b6, b_t), 1)
        else:
            G, b = G6, b6
        R_rows = G.shape[1]
        # pseudo-inverse through the symmetric eigendecomposition of A A^T, for the regions that
        # hold contact slots (the others have no unknown: y = 0, rank 0, residual |b|)
        solved = lay["solved"]
        Gm = G.index_select(0, solved).permute(0, 3, 1, 2)  # (S', N, R, R)
        Gm = 0.5 * (Gm + Gm.transpose(-1, -2))
        if self.solver == "jacobi":
            n_solved = solved.shape[0]
            Gs = Gm.permute(2, 3, 0, 1).reshape(R_rows, R_rows, -1)  # batch-last (R, R, S'N)
            lam, V = _jacobi.jacobi_eigh_bl(Gs, self.jacobi_sweeps)
            lam = lam.reshape(R_rows, n_solved, -1).permute(1, 2, 0)  # unsorted
            V = V.reshape(R_rows, R_rows, n_solved, -1).permute(2, 3, 0, 1)
        else:
            lam, V = torch.linalg.eigh(Gm)
        rtol = R_rows * torch.finfo(dtype).eps if rank_rtol is None else rank_rtol
        lam_max = lam.amax(-1, keepdim=True).clamp_min(0)
        keep = (lam > rtol * lam_max) & (lam > 0)
        inv = torch.where(
            keep, 1.0 / torch.where(keep, lam, torch.ones_like(lam)), torch.zeros_like(lam)
        )
        rank = torch.zeros(S, n, dtype=torch.long, device=q.device)
        rank = rank.index_copy(0, solved, keep.sum(-1)).T  # (N, S)
        bm = b.index_select(0, solved).permute(0, 2, 1)  # (S', N, R)
        y_s = (V * inv.unsqueeze(-2)) @ (V.transpose(-1, -2) @ bm.unsqueeze(-1))  # (S', N, R, 1)
        y = b.new_zeros(S, R_rows, n).index_copy(0, solved, y_s.squeeze(-1).permute(0, 2, 1))
        # each slot's wrench w_k = P_k Y_k^T y_region(k)
        y_k = y.index_select(0, lay["region"])  # (K, R, N)
        Yty = _dyn._mv_bl(X.transpose(1, 2), y_k[:, :6])
        if m:
            Tk_own = (T.permute(2, 0, 1, 3, 4) * onehot.T.reshape(K, S, 1, 1, 1)).sum(
                1
            )  # (K, m, 6, N)
            Yty = Yty + (Tk_own * y_k[:, 6:].unsqueeze(2)).sum(1)
        w = _dyn._mv_bl(P, Yty)  # (K, 6, N)
        if wk is not None:
            w = w + wk
        residual = (b - torch.einsum("sijn,sjn->sin", G, y)).norm(dim=1).T  # (N, S)
        n_unk = lay["n_unknowns"].unsqueeze(-1) * active.T * (1 - is_["known"].unsqueeze(-1))
        unknowns = (onehot @ n_unk).round().to(torch.long).T  # (N, S)
        # backward pass: internal wrenches with the estimated contacts; joints on the near side
        # of a sensor see its reading (Sec. 2.3)
        W_est = self._contact_wrenches_root(fp, lay, posb, w)
        F = _dyn.subtree_sum(model, f - self._scatter_bodies(W_est, lay))
        for i in self._deep_first:
            delta = W_root[i] - F[self.sensors[i].child_body]
            F = F + self._anc[i].reshape(-1, 1, 1) * delta
        tau = model.q_to_body @ (fp.S * F).sum(1)  # (nv, N)
        cov = None
        if cov_in is not None:
            # w_k = P_k Y_k^T (A A^T)^+ b and b's first 6 rows hold minus the own reading:
            # cov(w_k) = M_k Sigma M_k^T with M_k = P_k Y_k^T (A A^T)^+[:, :6]
            Ginv = (V * inv.unsqueeze(-2)) @ V.transpose(-1, -2)  # (S', N, R, R)
            Gk = Ginv.index_select(0, torch.searchsorted(solved, lay["region"]))  # (K, N, R, R)
            Pm, Xm = P.permute(0, 3, 1, 2), X.permute(0, 3, 1, 2)  # (K, N, 6, 6)
            M = Xm.transpose(-1, -2) @ Gk[..., :6, :6]
            if m:
                M = M + Tk_own.permute(0, 3, 2, 1) @ Gk[..., 6:, :6]  # (K, N, 6, m) @ (m, 6)
            M = Pm @ M
            Sig = cov_in.permute(1, 0, 2, 3).index_select(0, lay["region"])  # (K, N, 6, 6)
            cov = (M @ Sig @ M.transpose(-1, -2)).permute(1, 0, 2, 3)
        return (
            w[:, :3].permute(2, 0, 1),
            w[:, 3:].permute(2, 0, 1),
            rank,
            unknowns,
            residual,
            tau.T,
            cov,
        )
