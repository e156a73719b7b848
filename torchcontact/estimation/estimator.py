"""The estimator's public façade: :class:`ContactEstimator` and its result :class:`ContactEstimate`.

The façade checks shapes, names the offending argument of a malformed call, and hands views of the
inputs to the layout's program (:mod:`torchcontact.estimation.programs`), which does the per-frame
work, value checks included, eagerly or as a generated kernel.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchcontact import dynamics as _dyn
from torchcontact import kernels
from torchcontact._internal import check_input, counts, flatten_batch, in_tracing
from torchcontact.constrained import FrictionCones, PreviousFrame
from torchcontact.contacts import KINDS, Contacts
from torchcontact.dynamics import BaseMotion
from torchcontact.errors import InputError
from torchcontact.estimation.layout import EstimationModel
from torchcontact.estimation.programs import program
from torchcontact.kernels.runner import run_program
from torchcontact.model import RobotModel

__all__ = ["ConeStatus", "ContactEstimate", "ContactEstimator"]


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
        status: ``(*B,)`` int64, 0 if ok, else bits of :data:`torchcontact.STATUS`; outputs of
            such frames are NaN, but for bit 256 (the constrained solve did not converge: its
            last iterate is kept).
        covariance: ``(*B, K, 6, 6)`` covariance of each slot's ``[force; moment]`` estimate
            (weighted or not) from the noise covariance, or None when not asked for or with
            ``constraints`` (the constrained estimate is not linear in the readings).
        cones: status of the friction-cone constrained estimate (``constraints=``), or None.
        nullspace: sensor -> ``(*B, u, u)`` orthonormal basis of the null space of ``A`` among
            the region's unknowns (``nullspace=True``), or None: the first ``nullity[sensor]``
            columns are the basis vectors (combinations of contact forces the sensors cannot tell
            apart), the rest zero. Rows follow :meth:`ContactEstimator.unknown_labels`.
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
    cones: ConeStatus | None = None
    nullspace: dict[str, Tensor] | None = None

    @property
    def nullity(self) -> dict[str, Tensor]:
        """Sensor -> ``(*B,)`` dimension of the null space of ``A``: ``unknowns - rank``."""
        return {s: self.unknowns[s] - self.rank[s] for s in self.rank}


class ConeStatus(NamedTuple):
    """Per-frame status of the friction-cone constrained estimate.

    Attributes:
        converged: sensor -> ``(*B,)`` bool: the interior-point iterations stopped (the
            iterate no longer moves) within the budget and the KKT residuals meet ``tol``.
        iterations: sensor -> ``(*B,)`` int64, the iterations run until then (the budget when
            it never stopped; 0 where the pseudo-inverse solution lies inside every cone, and
            for a region without unknowns).
        active: ``(*B, K)`` bool, the slot's cone constraint binds (its force is on the cone's
            boundary or at its apex).
    """

    converged: dict[str, Tensor]
    iterations: dict[str, Tensor]
    active: Tensor


class ContactEstimator:
    """Estimate contact wrenches and joint torques from F/T readings, batched over frames.

    Args:
        model: the robot; its dtype and device are those of the computation, ``model.gravity``
            its gravity on a fixed base.
        sensors: names of F/T sensors of ``model.ft_sensors`` to use (default: all of them).
            Sensors not used do not cut the tree.
        rank_rtol: rank tolerance of the solve, relative to the largest diagonal entry of
            ``A A^T`` (default :data:`torchcontact.solve.RANK_RTOL` of the model's dtype).
        velocity_margin: a frame whose ``|qd|`` exceeds ``velocity_margin`` times a joint's URDF
            velocity limit gets status bit 64 (implausible input); None (default) disables the
            check (the log CLI enables it).
        ft_range: sensor name -> its measuring range, a number or 6 numbers ``[N; N m]``: a
            reading beyond it gets status bit 64.
        backend: ``"auto"``, ``"eager"``, ``"cpu"`` or ``"cuda"`` (:mod:`torchcontact.kernels`):
            the default runs a generated kernel once it is built (in the background, a few
            seconds; cached on disk) and eager torch until then.

    Raises:
        InputError: an unknown sensor name, a robot without F/T sensors, a bad ``ft_range``.

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
        *,
        rank_rtol: float | None = None,
        velocity_margin: float | None = None,
        ft_range: Mapping[str, float | Sequence[float]] | None = None,
        backend: str = "auto",
    ) -> None:
        names = list(model.ft_sensors) if sensors is None else list(sensors)
        if backend not in kernels.BACKENDS:
            raise InputError(f"unknown backend {backend!r}; expected one of {kernels.BACKENDS}")
        self.model = model
        self.sensor_names = tuple(names)
        self.rank_rtol = rank_rtol
        self.velocity_margin = velocity_margin
        self.ft_range = dict(ft_range or {})
        self.backend = backend
        self._layouts: dict = {}
        base = self.layout((), ())  # validates the sensors and the checks' settings
        self.sensors = base.sensors

    @property
    def region(self) -> tuple[int, ...]:
        """Per body, the index (in ``sensor_names``) of the region it lies in, -1 for the root."""
        return self.layout((), ()).region_of_body

    def layout(self, links: Sequence[str], kinds: Sequence[str]) -> EstimationModel:
        """The :class:`~torchcontact.estimation.EstimationModel` of a slot layout (cached).

        Raises:
            InputError: an unknown kind or link, or a link outside every sensor's subtree.
        """
        key = (tuple(links), tuple(kinds))
        if key not in self._layouts:
            self._layouts[key] = EstimationModel.build(
                self.model, self.sensor_names, key[0], key[1], self.rank_rtol,
                self.velocity_margin, self.ft_range,
            )  # fmt: skip
        return self._layouts[key]

    def estimate(
        self,
        q: Tensor,
        qd: Tensor,
        qdd: Tensor,
        ft: Mapping[str, Tensor],
        contacts: Contacts,
        *,
        base: BaseMotion | None = None,
        tau_measured: Tensor | None = None,
        tau_mask: Tensor | None = None,
        ft_covariance: Mapping[str, Tensor] | None = None,
        tau_variance: Tensor | None = None,
        weighted: bool = True,
        chunk_size: int | None = 8192,
        backend: str | None = None,
        constraints: FrictionCones | None = None,
        warm_start: tuple[Tensor, Tensor] | PreviousFrame | None = None,
        nullspace: bool = False,
        covariance: bool = True,
    ) -> ContactEstimate:
        """Estimate the contacts of every frame (Del Prete et al. 2012, Sec. 2).

        Args:
            q: ``(*B, nv)`` joint positions, rad or m, ``model.joint_names`` order.
            qd: ``(*B, nv)`` joint velocities.
            qdd: ``(*B, nv)`` joint accelerations.
            ft: sensor name -> ``(*B, 6)`` reading ``[force (N); moment (N m)]`` in the sensor's
                declared frame and measure direction.
            contacts: the contact slots (:class:`~torchcontact.Contacts`), ``(*B, K, ...)`` data.
            base: IMU measurement of a moving base (:class:`~torchcontact.BaseMotion`); without
                it the base is fixed and ``model.gravity`` applies.
            tau_measured: ``(*B, nv)`` measured joint torques (joint torque sensors), N m or N;
                each measured coordinate inside a sensor region adds an equation.
            tau_mask: ``(nv,)`` or ``(*B, nv)`` bool, which joints have a torque measurement
                (default: all finite entries of ``tau_measured``).
            ft_covariance: sensor name -> ``(6, 6)`` or ``(*B, 6, 6)`` covariance of its reading
                noise (sensor frame, N^2, N^2 m, N^2 m^2), symmetric positive definite. With
                ``weighted`` (the default) it weighs the solve: each region's rows are whitened by
                their noise, ``x* = pinv(L^-1 A) L^-1 b`` with ``Sigma = L L^T``, the weighted
                least-squares estimate of minimum norm ``|x|`` (:mod:`torchcontact.solve`), and
                every used sensor needs one. Without constraints ``covariance`` of the result is
                the first-order covariance of the estimate from each region's own rows (nested
                sensors' noise is not included).
            tau_variance: ``(nv,)`` or ``(*B, nv)`` noise variance of each measured joint torque
                (N^2 m^2 or N^2), > 0: the weight and noise of the torque rows. Needed with
                ``tau_measured`` and a weighted ``ft_covariance``; without it an unweighted
                propagation leaves the torque rows' noise out.
            weighted: with ``ft_covariance``, weigh the solve by it (True) or keep the paper's
                unit-weight ``pinv(A) b`` and only propagate the noise (False).
            chunk_size: frames per eager call (bounds memory); None for one go. Kernels stream
                any batch in one call.
            backend: overrides the estimator's backend for this call.
            constraints: :class:`~torchcontact.constrained.FrictionCones`: estimate with every
                pushing slot's force inside its friction cone (``contacts.normals``,
                ``friction`` or ``cone_angle``, ``pushing``): by default the maximum a
                posteriori estimate under a stated prior (``FrictionCones.objective``; the
                readings weighted by ``ft_covariance`` when given), or ``min |A x - b|^2 + eps
                |x|^2``, by a fixed-budget interior-point method (:mod:`torchcontact.constrained`);
                the result's ``cones`` holds its status, and a frame that does not converge
                gets status bit 256. None: the paper's pseudo-inverse.
            warm_start: ``(force, moment)``, each ``(*B, K, 3)`` (link frame, e.g. a previous
                frame's estimate): the constrained solver's starting point (frames with
                non-finite values start from the pseudo-inverse solution; a frame that does not
                converge from it restarts from there, so the start never changes the answer); or
                :class:`~torchcontact.constrained.PreviousFrame`: the batch is a time series and
                each frame starts from its predecessor's estimate (computed in waves).
            nullspace: also return each region's null-space basis (``nullspace`` of the result).
            covariance: with ``ft_covariance`` and no constraints, also return the estimate's
                ``covariance`` (False: only weigh the solve by the noise, a cheaper program).

        Returns:
            :class:`ContactEstimate`.

        Raises:
            InputError: wrong shapes/dtype/device, a missing sensor reading, a contact on an
                unknown link or outside every sensor's subtree; with ``constraints``: missing
                normals or friction, a zero normal or a friction coefficient that is not a
                positive finite number on an active pushing slot. Non-finite values, zero-length
                directions and implausible inputs do not raise: the frame gets a ``status`` and
                NaN outputs, the other frames are unaffected; a covariance that is not symmetric
                positive definite, a missing sensor covariance or ``tau_variance`` of a weighted
                solve, a variance that is not > 0.
        """
        model, K, nv = self.model, contacts.K, self.model.nv
        dtype, device = model.dtype, model.device
        em = self.layout(contacts.links, contacts.kinds)
        for name, x in (("q", q), ("qd", qd), ("qdd", qdd)):
            check_input(name, x, (nv,), model, f"(*B, {nv})", finite=False)
        batch = q.shape[:-1]
        if qd.shape[:-1] != batch or qdd.shape[:-1] != batch:
            raise InputError("q, qd, qdd must share their batch shape")
        n = math.prod(batch)
        missing = [s for s in self.sensor_names if s not in ft]
        if missing:
            raise InputError(f"ft is missing readings of sensors {missing} (keys: {list(ft)})")
        extra = [s for s in ft if s not in self.sensor_names]
        if extra:
            raise InputError(f"ft has readings of unknown or unused sensors {extra}")

        def per_frame(name: str, x: Tensor | None, trailing: tuple[int, ...]) -> Tensor | None:
            if x is None:
                return None
            shape = f"(*B, {', '.join(map(str, trailing))})"
            check_input(name, x, trailing, model, shape, finite=False)
            if x.shape[: x.dim() - len(trailing)] != batch:
                raise InputError(
                    f"{name} must be {shape} with B={tuple(batch)}, got {tuple(x.shape)}"
                )
            return flatten_batch(x, batch, len(trailing)).reshape(n, -1)

        tensors = {k: flatten_batch(x, batch, 1) for k, x in (("q", q), ("qd", qd), ("qdd", qdd))}
        readings = [per_frame(f"ft[{s!r}]", ft[s], (6,)) for s in self.sensor_names]
        tensors["ft"] = readings[0] if len(readings) == 1 else torch.cat(readings, -1)
        tensors["positions"] = per_frame("contacts.positions", contacts.positions, (K, 3))
        if "force_dir" in em.kinds:
            if contacts.directions is None:
                raise InputError("contacts.directions is required for force_dir slots")
            tensors["directions"] = per_frame("contacts.directions", contacts.directions, (K, 3))
        if "known" in em.kinds:
            if contacts.wrenches is None:
                raise InputError("contacts.wrenches is required for known slots")
            tensors["wrenches"] = per_frame("contacts.wrenches", contacts.wrenches, (K, 6))
        if contacts.active is not None:
            act = contacts.active
            if not isinstance(act, Tensor) or act.shape != (*batch, K):
                raise InputError(
                    f"contacts.active must be a (*B, {K}) tensor, got {getattr(act, 'shape', act)}"
                )
            tensors["active"] = act.reshape(n, K).to(device=device, dtype=dtype)
        else:
            tensors["active"] = torch.ones(n, K, dtype=dtype, device=device)
        if base is not None:
            for k in BaseMotion._fields:
                tensors[k] = per_frame(f"base.{k}", getattr(base, k), (3,))
        if tau_measured is not None:
            tensors["tau_measured"] = per_frame("tau_measured", tau_measured, (nv,))
            if tau_mask is None:
                mask = torch.isfinite(tensors["tau_measured"])
            else:
                mask = tau_mask.to(device=device, dtype=torch.bool).expand(*batch, nv)
            tensors["tau_mask"] = mask.reshape(n, nv).to(dtype)
        weighted = bool(weighted) and ft_covariance is not None
        tau_noise = False
        if ft_covariance is not None:
            tensors["ft_cov"] = _noise_inputs(self, ft_covariance, batch, weighted)
            if tau_variance is not None and tau_measured is not None:
                tensors["tau_var"] = _tau_variance(tau_variance, batch, nv, model)
                tau_noise = True
            elif weighted and tau_measured is not None:
                raise InputError(
                    "tau_variance is needed to weigh the measured joint torques (tau_measured)"
                    " against the F/T readings; or pass weighted=False"
                )
        elif tau_variance is not None:
            raise InputError("tau_variance needs ft_covariance (the noise of the F/T readings)")
        cone_flags = None
        if constraints is not None:
            if not isinstance(constraints, FrictionCones):
                raise InputError(
                    f"constraints must be a torchcontact.constrained.FrictionCones, got"
                    f" {type(constraints).__name__}"
                )
            cone_flags = constraints.program_flags(dtype)
            tensors.update(_cone_inputs(contacts, em.kinds, batch, tensors["active"], model))
            if isinstance(warm_start, PreviousFrame):
                if warm_start.before is not None:
                    pair = warm_start.before
                    if not isinstance(pair, (tuple, list)) or len(pair) != 2:
                        raise InputError("PreviousFrame.before must be a (force, moment) pair")
                    for name, x in zip(("force", "moment"), warm_start.before, strict=True):
                        check_input(f"PreviousFrame.before {name}", x, (K, 3), model,
                                    f"({K}, 3)", finite=False)  # fmt: skip
                        if x.dim() != 2:
                            raise InputError(f"PreviousFrame.before {name} must be ({K}, 3)")
            elif warm_start is not None:
                if not isinstance(warm_start, (tuple, list)) or len(warm_start) != 2:
                    raise InputError("warm_start must be a (force, moment) pair of (*B, K, 3)")
                wf = per_frame("warm_start force", warm_start[0], (K, 3)).reshape(n, K, 3)
                wm = per_frame("warm_start moment", warm_start[1], (K, 3)).reshape(n, K, 3)
                tensors["warm"] = torch.cat([wf, wm], -1).reshape(n, 6 * K)
        elif warm_start is not None:
            raise InputError("warm_start needs constraints (it starts the constrained solver)")
        waves = warm_start if isinstance(warm_start, PreviousFrame) else None
        with_cov = ft_covariance is not None and cone_flags is None and bool(covariance)
        if not with_cov and not weighted:
            tensors.pop("ft_cov", None)
            tensors.pop("tau_var", None)
        prog = program(em, "estimate", base is not None, tau_measured is not None, with_cov,
                       cone_flags, "warm" in tensors or waves is not None, bool(nullspace),
                       weighted, tau_noise)  # fmt: skip
        backend = self.backend if backend is None else backend
        if waves is None:
            out = run_program(prog, tensors, backend, chunk_size)
        else:
            out = _run_waves(prog, tensors, waves, K, backend, chunk_size)
        rank = counts(out["rank"])
        unknowns = counts(out["unknowns"])
        ident = rank == unknowns
        names = self.sensor_names
        return ContactEstimate(
            force=out["force"].reshape(*batch, K, 3),
            moment=out["moment"].reshape(*batch, K, 3),
            rank={s: rank[:, i].reshape(batch) for i, s in enumerate(names)},
            unknowns={s: unknowns[:, i].reshape(batch) for i, s in enumerate(names)},
            residual={s: out["residual"][:, i].reshape(batch) for i, s in enumerate(names)},
            identifiable={s: ident[:, i].reshape(batch) for i, s in enumerate(names)},
            joint_torques=out["tau"].reshape(*batch, nv),
            status=counts(out["status"][:, 0]).reshape(batch),
            covariance=out["cov"].reshape(*batch, K, 6, 6) if with_cov else None,
            cones=None if cone_flags is None else ConeStatus(
                {s: out["converged"][:, i].reshape(batch) > 0.5 for i, s in enumerate(names)},
                {s: counts(out["iterations"][:, i]).reshape(batch)
                 for i, s in enumerate(names)},
                out["cone_active"].reshape(*batch, K) > 0.5,
            ),
            nullspace=None if not nullspace else _split_nullspace(em, out["nullspace"], batch),
        )  # fmt: skip

    def unknown_labels(self, contacts: Contacts) -> dict[str, list[str]]:
        """Sensor -> names of its region's unknowns, the rows of ``ContactEstimate.nullspace``.

        Example:
            >>> import torchcontact as tc
            >>> est = tc.ContactEstimator(tc.RobotModel.from_urdf(tc.robots.tcarm_path()))
            >>> pos = torch.zeros(1, 3, dtype=torch.float64)
            >>> est.unknown_labels(tc.Contacts(["hand_skin"], ["force"], pos))["base_ft"]
            ['0:hand_skin.fx', '0:hand_skin.fy', '0:hand_skin.fz']
        """
        em = self.layout(contacts.links, contacts.kinds)
        names = {"force": ("fx", "fy", "fz"), "force_dir": ("f",),
                 "wrench": ("fx", "fy", "fz", "mx", "my", "mz"), "known": ()}  # fmt: skip
        return {
            s: [f"{k}:{em.slots[k].link}.{c}" for k in reg.slots for c in names[em.slots[k].kind]]
            for s, reg in zip(self.sensor_names, em.regions, strict=True)
        }

    def outside_cones(self, contacts: Contacts, force: Tensor, rtol: float = 1e-6) -> Tensor:
        """Which forces lie outside their friction cones (e.g. an unconstrained estimate's).

        The cone of a slot is that of :class:`~torchcontact.constrained.FrictionCones`: active,
        pushing ``force``/``wrench`` slots with ``contacts.normals`` (outward) and
        ``contacts.friction`` or ``cone_angle``; ``f`` is inside when ``|f_t| <= mu f_n`` with
        ``f_n = -n . f``, to ``rtol |f|``.

        Args:
            contacts: the slots, ``(*B, K, ...)`` data.
            force: ``(*B, K, 3)`` forces, link frame, N.
            rtol: tolerance relative to ``|f|``.

        Returns:
            ``(*B, K)`` bool: the slot has a cone and its force lies outside it (False where
            it has none, and on non-finite values).

        Raises:
            InputError: as :meth:`estimate` with ``constraints``: missing normals or friction,
                a zero normal, a friction that is not finite and > 0 on an active pushing slot.

        Example:
            >>> import torchcontact as tc
            >>> est = tc.ContactEstimator(tc.RobotModel.from_urdf(tc.robots.tcarm_path()))
            >>> z = torch.zeros(2, 1, 3, dtype=torch.float64)
            >>> n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(2, 1, 3)
            >>> c = tc.Contacts(["hand_skin"], ["force"], z, normals=n, friction=0.5)
            >>> f = torch.tensor([[[0.4, 0, -1.0]], [[0.6, 0, -1.0]]], dtype=torch.float64)
            >>> est.outside_cones(c, f).tolist()
            [[False], [True]]
        """
        model, K = self.model, contacts.K
        em = self.layout(contacts.links, contacts.kinds)
        check_input("force", force, (K, 3), model, f"(*B, {K}, 3)", finite=False)
        batch = force.shape[:-2]
        n = math.prod(batch)
        if contacts.active is None:
            active = torch.ones(n, K, dtype=model.dtype, device=model.device)
        else:
            active = contacts.active.reshape(n, K).to(model.dtype)
        cone = _cone_inputs(contacts, em.kinds, batch, active, model)
        coned = torch.tensor([k in ("force", "wrench") for k in em.kinds], dtype=torch.bool,
                             device=model.device)  # fmt: skip
        has = (cone["pushing"] > 0.5) & (active > 0.5) & coned
        nrm = cone["normals"].reshape(n, K, 3)
        nrm = nrm / nrm.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(model.dtype).tiny)
        f = force.reshape(n, K, 3).to(model.dtype)
        fn = -(f * nrm).sum(-1)
        ft = (f + fn[..., None] * nrm).norm(dim=-1)
        out = has & (ft - cone["friction"] * fn > rtol * f.norm(dim=-1))
        return out.reshape(*batch, K)

    def predict_ft(
        self,
        q: Tensor,
        qd: Tensor,
        qdd: Tensor,
        contacts: Contacts,
        *,
        base: BaseMotion | None = None,
        backend: str | None = None,
    ) -> dict[str, Tensor]:
        """F/T readings the model predicts for known contact wrenches (forward model, simulation).

        Every active slot's ``contacts.wrenches`` is applied, whatever its kind; with no active
        slot this is the contact-free prediction that calibration and residual learning use.

        Args:
            q: ``(*B, nv)`` joint positions.
            qd: ``(*B, nv)`` joint velocities.
            qdd: ``(*B, nv)`` joint accelerations.
            contacts: slots with ``wrenches`` ``(*B, K, 6)`` (link frame, moment about the point).
            base: IMU measurement of a moving base.
            backend: overrides the estimator's backend for this call.

        Returns:
            sensor name -> ``(*B, 6)`` reading ``[force; moment]`` in its frame and direction.

        Raises:
            InputError: wrong shapes, dtype or device, non-finite inputs, missing wrenches.
        """
        model, K = self.model, contacts.K
        batch, tensors = _dyn._prepare(model, q, qd, qdd, base)
        n = math.prod(batch)
        em = self.layout(contacts.links, ("known",) * K)
        if K and contacts.wrenches is None:
            raise InputError("predict_ft needs contacts.wrenches")
        like = tensors["q"]
        if K:
            for name, x, feat in (("positions", contacts.positions, 3),
                                  ("wrenches", contacts.wrenches, 6)):  # fmt: skip
                check_input(f"contacts.{name}", x, (K, feat), model, f"(*B, {K}, {feat})")
                if x.shape[:-2] != batch:
                    raise InputError(f"contacts.{name} must be (*B, {K}, {feat}) with B={batch}")
            tensors["positions"] = flatten_batch(contacts.positions, batch, 2).reshape(n, 3 * K)
            tensors["wrenches"] = flatten_batch(contacts.wrenches, batch, 2).reshape(n, 6 * K)
            act = contacts.active
            tensors["active"] = (act.reshape(n, K).to(like) if act is not None
                                 else like.new_ones(n, K))  # fmt: skip
        else:
            tensors.update(positions=like.new_zeros(n, 0), wrenches=like.new_zeros(n, 0),
                           active=like.new_zeros(n, 0))  # fmt: skip
        prog = program(em, "predict", base is not None)
        out = run_program(prog, tensors, self.backend if backend is None else backend, 16384)
        ft = out["ft"]
        return {s: ft[:, 6 * i : 6 * i + 6].reshape(*batch, 6)
                for i, s in enumerate(self.sensor_names)}  # fmt: skip


def _run_waves(
    prog: kernels.Program,
    tensors: dict[str, Tensor],
    warm: PreviousFrame,
    K: int,
    backend: str,
    chunk_size: int | None,
) -> dict[str, Tensor]:
    """Run the constrained program in waves, each frame warm-started from its predecessor.

    Frames ``j, j + S, j + 2 S, ...`` form wave ``j`` (``S = ceil(n / warm.wave)``): the ``j``-th
    frame of every block of ``S`` consecutive frames; wave ``j`` starts from wave ``j - 1``'s
    estimates, wave 0 cold but for frame 0 (``warm.before``).
    """
    first = next(iter(tensors.values()))
    n = first.shape[0]
    S = max(1, -(-n // warm.wave))
    floats = (torch.float32, torch.float64)
    if backend == "auto" and n >= kernels.AUTO_BUILD_MIN_FRAMES and first.dtype in floats:
        # the waves are smaller than the batch: start the background build for the batch
        kernels.compiled(prog, first.dtype, first.device, wait=False)
    out: dict[str, Tensor] = {}
    prev = None
    for j in range(min(S, n)):
        rows = slice(j, n, S)
        sub = {k: v[rows] for k, v in tensors.items()}
        m = sub["q"].shape[0]
        start = first.new_full((m, 6 * K), float("nan"))
        if prev is not None:
            start = prev[:m]  # the previous wave has as many rows or one more
        elif warm.before is not None:
            start[0] = torch.cat([warm.before[0], warm.before[1]], -1).reshape(6 * K)
        sub["warm"] = start
        o = run_program(prog, sub, backend, chunk_size)
        for k, v in o.items():
            if k not in out:
                out[k] = v.new_empty(n, v.shape[1])
            out[k][rows] = v
        prev = torch.cat([o["force"].reshape(m, K, 3), o["moment"].reshape(m, K, 3)], -1)
        prev = prev.reshape(m, 6 * K)
    return out


#: Relative asymmetry ``max |C - C^T| / max |C|`` a covariance may have, per dtype.
_SYM_RTOL = {torch.float64: 1e-9, torch.float32: 1e-5}


def _noise_inputs(
    est: ContactEstimator, ft_covariance: Mapping[str, Tensor], batch: torch.Size, weighted: bool
) -> Tensor:
    """``ft_cov (N, 36 S)`` of the program, each covariance checked symmetric positive definite.

    Raises:
        InputError: an unknown sensor, a bad shape, NaN, a matrix that is not symmetric positive
            definite, or (``weighted``) a used sensor without a covariance.
    """
    model, names = est.model, est.sensor_names
    n, S = math.prod(batch), len(names)
    if not isinstance(ft_covariance, Mapping):
        raise InputError("ft_covariance must be a mapping: sensor name -> (6, 6) covariance")
    extra = [s for s in ft_covariance if s not in names]
    if extra:
        raise InputError(f"ft_covariance names unknown or unused sensors {extra} (sensors:"
                         f" {list(names)})")  # fmt: skip
    missing = [s for s in names if s not in ft_covariance]
    if weighted and missing:
        raise InputError(
            f"ft_covariance is missing sensors {missing}: a weighted solve needs the noise of"
            " every sensor used (or pass weighted=False to only propagate the noise given)"
        )
    cov = torch.zeros(n, S, 6, 6, dtype=model.dtype, device=model.device)
    for i, s in enumerate(names):
        if s not in ft_covariance:
            continue
        c = ft_covariance[s]
        name = f"ft_covariance[{s!r}]"
        check_input(name, c, (6, 6), model, "(6, 6) or (*B, 6, 6)")
        if c.dim() > 2 and tuple(c.shape[:-2]) != tuple(batch):
            raise InputError(f"{name} must be (6, 6) or (*B, 6, 6) with B={tuple(batch)}, got"
                             f" {tuple(c.shape)}")  # fmt: skip
        if not in_tracing():
            _check_spd(name, c)
        cov[:, i] = c.expand(*batch, 6, 6).reshape(n, 6, 6)
    return cov.reshape(n, 36 * S)


def _check_spd(name: str, c: Tensor) -> None:
    """Raise :class:`InputError` unless every matrix of ``c (*, 6, 6)`` is symmetric and PD."""
    flat = c.reshape(-1, 6, 6)
    scale = flat.abs().amax((-2, -1))
    asym = (flat - flat.transpose(-1, -2)).abs().amax((-2, -1))
    bad = asym > _SYM_RTOL.get(c.dtype, 1e-9) * scale
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        where = f" (matrix {i})" if flat.shape[0] > 1 else ""
        raise InputError(
            f"{name} is not symmetric{where}: max |C - C^T| = {float(asym[i]):.3g} for entries"
            f" up to {float(scale[i]):.3g}; a covariance must be symmetric positive definite"
        )
    _, info = torch.linalg.cholesky_ex(flat)
    if bool((info != 0).any()):
        i = int((info != 0).nonzero()[0, 0])
        where = f" (matrix {i})" if flat.shape[0] > 1 else ""
        lam = float(torch.linalg.eigvalsh(flat[i]).min())
        raise InputError(
            f"{name} is not positive definite{where}: smallest eigenvalue {lam:.3g}; a"
            " covariance must be symmetric positive definite (every reading axis has noise)"
        )


def _tau_variance(v: Tensor, batch: torch.Size, nv: int, model: RobotModel) -> Tensor:
    """``tau_var (N, nv)``: measured-torque noise variances, checked finite and > 0."""
    check_input("tau_variance", v, (nv,), model, f"({nv},) or (*B, {nv})")
    if v.dim() > 1 and tuple(v.shape[:-1]) != tuple(batch):
        raise InputError(f"tau_variance must be ({nv},) or (*B, {nv}) with B={tuple(batch)}, got"
                         f" {tuple(v.shape)}")  # fmt: skip
    if not in_tracing() and bool((v <= 0).any()):
        j = int((v <= 0).nonzero()[0, -1])
        raise InputError(f"tau_variance must be > 0; joint {model.joint_names[j]!r} has"
                         f" {float(v.reshape(-1, nv)[0, j])!r}")  # fmt: skip
    return v.expand(*batch, nv).reshape(math.prod(batch), nv)


def _split_nullspace(em: EstimationModel, flat: Tensor, batch: torch.Size) -> dict[str, Tensor]:
    out, start = {}, 0
    for s, reg in zip(em.sensor_names, em.regions, strict=True):
        u = sum(KINDS[em.slots[k].kind] for k in reg.slots)
        out[s] = flat[:, start : start + u * u].reshape(*batch, u, u)
        start += u * u
    return out


def _cone_inputs(
    contacts: Contacts, kinds: Sequence[str], batch: torch.Size, active: Tensor, model: RobotModel
) -> dict[str, Tensor]:
    """``normals (N, 3K)``, ``friction (N, K)``, ``pushing (N, K)`` of the constrained program.

    Raises:
        InputError: bad shapes; missing normals or friction for pushing force/wrench slots; a
            zero normal or a friction coefficient that is not finite and > 0 on an active
            pushing slot (NaN normals are left to the per-frame status).
    """
    n, K = active.shape
    dtype, device = model.dtype, model.device

    def per_slot(name: str, v: object, default: float) -> Tensor:
        if v is None:
            return torch.full((n, K), default, dtype=dtype, device=device)
        if not isinstance(v, Tensor):
            return torch.full((n, K), float(v), dtype=dtype, device=device)
        if v.shape not in ((K,), (*batch, K)):
            raise InputError(f"contacts.{name} must be (K,) = ({K},) or (*B, K), got"
                             f" {tuple(v.shape)}")  # fmt: skip
        return v.to(device=device, dtype=dtype).expand(*batch, K).reshape(n, K)

    pushing = per_slot("pushing", contacts.pushing, 1.0)
    pushing = pushing * torch.tensor([k != "known" for k in kinds], dtype=dtype, device=device)
    # dtype given: with no slot (K = 0) ``torch.tensor([])`` would be float, and bool & float fails
    coned = torch.tensor([k in ("force", "wrench") for k in kinds], dtype=torch.bool, device=device)
    need = (pushing > 0.5) & coned
    live = need & (active > 0.5)
    if contacts.normals is None:
        if bool(need.any()):
            slots = sorted({int(k) for k in need.nonzero()[:, 1].tolist()})
            raise InputError(f"constraints need contacts.normals for the pushing slots {slots}")
        normal = torch.zeros(n, 3 * K, dtype=dtype, device=device)
    else:
        check_input("contacts.normals", contacts.normals, (K, 3), model, f"(*B, {K}, 3)",
                    finite=False)  # fmt: skip
        if contacts.normals.shape[:-2] != batch:
            raise InputError(f"contacts.normals must be (*B, {K}, 3) with B={tuple(batch)}")
        nrm = contacts.normals.reshape(n, K, 3)
        zero = live & (nrm.abs().sum(-1) == 0)
        if bool(zero.any()):
            f, k = zero.nonzero()[0].tolist()
            raise InputError(
                f"contacts.normals: zero normal on pushing slot {k} ({contacts.links[k]!r}) in"
                f" frame {f}; a friction cone needs a surface normal of nonzero length"
            )
        normal = nrm.reshape(n, 3 * K)
    mu_raw = contacts.friction_coefficient()
    if mu_raw is None and bool(need.any()):
        raise InputError("constraints need contacts.friction (or contacts.cone_angle)")
    name = "cone_angle" if contacts.cone_angle is not None else "friction"
    mu = per_slot(name, mu_raw, 1.0)
    bad = live & ~(torch.isfinite(mu) & (mu > 0))
    if bool(bad.any()):
        f, k = bad.nonzero()[0].tolist()
        raise InputError(
            f"contacts.{name}: slot {k} ({contacts.links[k]!r}) in frame {f} has friction"
            f" coefficient {float(mu[f, k])!r}; it must be a finite number > 0"
            " (cone half-angle in (0, pi/2))"
        )
    return {"normals": normal, "friction": mu, "pushing": pushing}
