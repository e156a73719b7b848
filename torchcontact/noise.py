"""The F/T reading noise a solve is weighted by: its specification and the value that carries it.

One parser for every place a user gives noise (``torchcontact estimate --ft-noise`` of a log run,
``torchcontact export estimator --ft-noise`` of a deployed graph or C library):
``SENSOR=SIGMA_F,SIGMA_M`` (standard deviations, N and N m), six numbers ``FX,FY,FZ,MX,MY,MZ``
or a driver profile with a datasheet ``[noise]`` (:mod:`torchcontact.drivers.profiles`). The
solve they weigh is :func:`torchcontact.solve.weighted_solve_program` (``docs/accuracy.md``). A
log run's other noise sources (its ``ft_cov`` column, profile metadata, contact-free frames) are
in :mod:`torchcontact.logs.noise`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from torchcontact.errors import InputError

__all__ = ["FTNoise", "SensorNoise", "fixed_noise", "parse_ft_noise", "profile_std"]


@dataclass(frozen=True)
class SensorNoise:
    """One sensor's noise and where it came from.

    Attributes:
        source: ``"--ft-noise"``, ``"profile NAME (--ft-noise)"``, ``"column ft_cov.<s>"``,
            ``"profile NAME (log metadata)"`` or ``"contact-free frames (N pairs)"``.
        std: ``(6,)`` standard deviations ``[N; N m]`` of a diagonal covariance, or None for the
            per-frame covariances of the log's column.
    """

    source: str
    std: tuple[float, ...] | None = None

    @property
    def column(self) -> bool:
        """The covariance is the log's per-frame ``ft_cov.<sensor>`` column."""
        return self.std is None


@dataclass(frozen=True)
class FTNoise:
    """The noise of every sensor of a run, or why the run is unweighted.

    Attributes:
        sensors: sensor -> :class:`SensorNoise` (every sensor in use when weighted).
        unweighted: why the solve is the unweighted ``pinv(A) b`` (None: weighted).
    """

    sensors: Mapping[str, SensorNoise] = field(default_factory=dict)
    unweighted: str | None = None

    @property
    def weighted(self) -> bool:
        """The solve is weighted by :attr:`sensors`."""
        return self.unweighted is None

    def column_sensors(self) -> list[str]:
        """Sensors whose covariance is the log's per-frame column."""
        return [s for s, n in self.sensors.items() if self.weighted and n.column]

    def covariances(self, ft_cov: Mapping[str, np.ndarray]) -> dict[str, np.ndarray] | None:
        """``ft_covariance`` of a chunk: sensor -> ``(6, 6)`` or ``(n, 6, 6)``; None: unweighted.

        Args:
            ft_cov: the chunk's per-frame covariances ``(n, 6, 6)`` of :meth:`column_sensors`.
        """
        if not self.weighted:
            return None
        out = {}
        for s, n in self.sensors.items():
            out[s] = ft_cov[s] if n.column else np.diag(np.square(np.asarray(n.std)))
        return out

    def summary(self) -> dict:
        """JSON-ready: ``{"weighted", "reason"?, "sensors": {s: {"source", "std"}}}``."""
        out: dict[str, Any] = {"weighted": self.weighted}
        if not self.weighted:
            out["reason"] = self.unweighted
        out["sensors"] = {
            s: {"source": n.source, "std": None if n.std is None else [float(v) for v in n.std]}
            for s, n in self.sensors.items()
        }
        return out

    def describe(self) -> str:
        """One line for the CLI: which noise weighted the solve, or why none did."""
        if not self.weighted:
            return f"unweighted ({self.unweighted})"
        return "weighted by " + ", ".join(f"{s}: {n.source}" for s, n in self.sensors.items())

    def metadata(self) -> str:
        """The output log's :data:`~torchcontact.logs.format.META_FT_NOISE` value."""
        return json.dumps(self.summary())


def _positive(values: Sequence[str], what: str) -> tuple[float, ...] | None:
    try:
        nums = tuple(float(v) for v in values)
    except ValueError:
        return None
    if not all(0 < v < math.inf for v in nums):
        raise InputError(
            f"--ft-noise {what}: a standard deviation must be a finite number > 0 (a covariance"
            f" must be symmetric positive definite), got {list(values)}"
        )
    return nums


def parse_ft_noise(values: Iterable[str] | None) -> dict[str, tuple[float, ...] | str]:
    """``--ft-noise`` values -> ``{sensor: (6,) standard deviations or a profile name}``.

    ``NAME=SIGMA_F,SIGMA_M`` (N, N m: forces and moments), ``NAME=FX,FY,FZ,MX,MY,MZ`` or
    ``NAME=PROFILE`` (a driver profile with a datasheet ``[noise]``: name or TOML path).

    Raises:
        InputError: not ``NAME=...``, a sensor given twice, 3-5 or 7+ numbers, a standard
            deviation that is not > 0.

    Example:
        >>> parse_ft_noise(["base_ft=0.1,0.005"])
        {'base_ft': (0.1, 0.1, 0.1, 0.005, 0.005, 0.005)}
    """
    out: dict[str, tuple[float, ...] | str] = {}
    for v in values or ():
        name, sep, rest = v.partition("=")
        name, rest = name.strip(), rest.strip()
        if not sep or not name or not rest:
            raise InputError(
                f"--ft-noise {v}: expected SENSOR=SIGMA_F,SIGMA_M, SENSOR=FX,FY,FZ,MX,MY,MZ"
                " (standard deviations, N and N m) or SENSOR=PROFILE"
            )
        if name in out:
            raise InputError(f"--ft-noise: sensor {name!r} given twice")
        parts = [p.strip() for p in rest.split(",")]
        nums = _positive(parts, v)
        if nums is None:
            if len(parts) > 1:
                raise InputError(f"--ft-noise {v}: {rest!r} is neither numbers nor a profile")
            out[name] = rest
        elif len(nums) == 2:
            out[name] = (nums[0],) * 3 + (nums[1],) * 3
        elif len(nums) == 6:
            out[name] = nums
        else:
            raise InputError(
                f"--ft-noise {v}: give 2 (SIGMA_F,SIGMA_M) or 6 standard deviations, got"
                f" {len(nums)}"
            )
    return out


def profile_std(name: str, where: str) -> tuple[float, ...]:
    """The datasheet noise ``(6,)`` std ``[N; N m]`` of a driver profile (name or TOML path).

    Raises:
        InputError: an unknown profile, or one without ``[noise]`` (``where`` starts the message).
    """
    from torchcontact.drivers.profiles import ProfileError, load_profile

    try:
        prof = load_profile(name)
    except ProfileError as exc:
        raise InputError(f"{where}: {exc}") from None
    if prof.noise_std is None:
        raise InputError(
            f"{where}: profile {prof.name!r} gives no datasheet noise ([noise].std); give the"
            " standard deviations instead (SENSOR=SIGMA_F,SIGMA_M)"
        )
    return prof.noise_std


def fixed_noise(
    ft_noise: Mapping[str, Sequence[float] | str] | Sequence[str],
    sensors: Sequence[str],
    robot_sensors: Sequence[str] | None = None,
) -> FTNoise:
    """The constant noise of every sensor of an exported estimator (``export --ft-noise``).

    The exported graphs and C libraries whiten each sensor's rows by a noise fixed at export
    (``docs/deployment.md``); unlike a log run there is no other source, so every sensor in use
    needs one.

    Args:
        ft_noise: ``--ft-noise`` strings (:func:`parse_ft_noise`) or their parsed form
            ``{sensor: (6,) standard deviations [N; N m] or a profile name}`` (2 numbers:
            ``SIGMA_F, SIGMA_M``).
        sensors: the sensors in use, in the estimator's order.
        robot_sensors: every F/T sensor of the robot (for the message; default ``sensors``).

    Returns:
        :class:`FTNoise` with a :class:`SensorNoise` (its ``std``) per sensor, in ``sensors``
        order.

    Raises:
        InputError: a malformed value, a standard deviation that is not > 0, a sensor the robot
            does not have or the estimator does not use, a sensor without noise, an unknown
            profile or one without ``[noise]``.

    Example:
        >>> fixed_noise(["base_ft=0.1,0.005"], ["base_ft"]).sensors["base_ft"].std
        (0.1, 0.1, 0.1, 0.005, 0.005, 0.005)
    """
    if isinstance(ft_noise, Mapping):
        given: dict[str, tuple[float, ...] | str] = {}
        for s, v in ft_noise.items():
            if isinstance(v, str):
                given[s] = v
                continue
            nums = _positive([str(x) for x in v], f"{s}={list(v)}")
            if nums is None or len(nums) not in (2, 6):
                raise InputError(f"--ft-noise {s}: give 2 (SIGMA_F,SIGMA_M) or 6 numbers")
            given[s] = nums if len(nums) == 6 else (nums[0],) * 3 + (nums[1],) * 3
    else:
        given = parse_ft_noise(ft_noise)
    everything = list(robot_sensors) if robot_sensors is not None else list(sensors)
    for s in given:
        if s not in everything:
            raise InputError(
                f"--ft-noise {s}: the robot has no F/T sensor {s!r} (its sensors: {everything})"
            )
        if s not in sensors:
            raise InputError(f"--ft-noise {s}: not a sensor of the estimator ({list(sensors)})")
    left = [s for s in sensors if s not in given]
    if left:
        raise InputError(
            f"--ft-noise: no noise for {left}; an exported estimator is weighted by every"
            " sensor's noise (give each sensor SENSOR=SIGMA_F,SIGMA_M, 6 numbers or a profile)"
        )
    out: dict[str, SensorNoise] = {}
    for s in sensors:
        g = given[s]
        if isinstance(g, str):
            out[s] = SensorNoise(f"profile {g} (--ft-noise)", profile_std(g, f"--ft-noise {s}"))
        else:
            out[s] = SensorNoise("--ft-noise", tuple(float(v) for v in g))
    return FTNoise(out)
