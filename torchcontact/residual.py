"""Learned correction of F/T readings: models of the contact-free residual, checkpoints, use.

On contact-free frames the residual ``r = ft_measured - ft_predicted`` (the reading the rigid-body
model predicts with no contact, :meth:`ContactEstimator.predict_ft`) collects what the model does
not know: sensor offset and drift, payload errors, cables and hoses. A small network
``r_hat(features)`` learns it; at estimation time the corrected reading ``ft - r_hat`` enters the
estimator's ``b`` (Del Prete et al. 2012, Sec. 2).

Models train and run in float32 and cast at their boundary: inputs of any floating dtype, outputs
in the input's dtype. The feature and target normalisation are buffers of the module, saved with
the weights, so a checkpoint cannot lose them.

Checkpoint directory (written by ``python -m training``):

- ``weights.safetensors``: the module's ``state_dict`` (float32 tensors, no pickle).
- ``checkpoint.json``: ``format`` (:data:`CHECKPOINT_FORMAT`), ``arch`` (constructor arguments),
  ``features`` (input names in order), ``joint_names``, ``sensor``, ``robot_sha256``,
  ``data_sha256``, ``weights_sha256`` (sha256 of the weights file), ``config`` and ``metrics``.

This module needs torch and safetensors only; the training pipeline lives in ``training/``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from torchcontact.errors import CheckpointError  # noqa: F401  (re-exported)

__all__ = [
    "CHECKPOINT_FORMAT",
    "CheckpointError",
    "ResidualCorrection",
    "ResidualGRU",
    "ResidualMLP",
    "build_residual_model",
    "feature_names",
    "load_residual_model",
    "save_residual_model",
]

#: Value of ``checkpoint.json["format"]``; a different value is a foreign checkpoint.
CHECKPOINT_FORMAT = "torchcontact.residual/1"
WEIGHTS_FILE = "weights.safetensors"
META_FILE = "checkpoint.json"


def feature_names(joint_names: Sequence[str], extra: Sequence[str] = ()) -> list[str]:
    """Default feature layout: ``q.<joint>``, ``qd.<joint>``, ``qdd.<joint>``, then extra columns.

    Example:
        >>> feature_names(["a", "b"], ["temperature"])
        ['q.a', 'q.b', 'qd.a', 'qd.b', 'qdd.a', 'qdd.b', 'temperature']
    """
    return [f"{p}.{j}" for p in ("q", "qd", "qdd") for j in joint_names] + list(extra)


class _Normalised(nn.Module):
    """Feature/target standardisation held as buffers (saved with the weights)."""

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__()
        self.in_features, self.out_features = in_features, out_features
        self.register_buffer("feature_mean", torch.zeros(in_features))
        self.register_buffer("feature_std", torch.ones(in_features))
        self.register_buffer("target_mean", torch.zeros(out_features))
        self.register_buffer("target_std", torch.ones(out_features))

    def set_normalisation(self, x: Tensor, y: Tensor) -> None:
        """Set the statistics from training features ``(N, F)`` and targets ``(N, out)``."""
        x, y = x.detach().float(), y.detach().float()
        self.feature_mean.copy_(x.mean(0))
        self.feature_std.copy_(x.std(0).clamp_min(1e-6))
        self.target_mean.copy_(y.mean(0))
        self.target_std.copy_(y.std(0).clamp_min(1e-6))

    def _in(self, x: Tensor) -> Tensor:
        if x.shape[-1] != self.in_features:
            raise ValueError(f"features: expected (..., {self.in_features}), got {tuple(x.shape)}")
        return (x.float() - self.feature_mean) / self.feature_std

    def _out(self, z: Tensor) -> Tensor:
        return z * self.target_std + self.target_mean


class ResidualMLP(_Normalised):
    """MLP ``r_hat = f(features)``: the default residual model.

    Args:
        in_features: number of features F.
        hidden: width of the hidden layers.
        layers: number of hidden layers.
        out_features: 6 (one wrench ``[force; moment]``).

    Example:
        >>> m = ResidualMLP(4, hidden=8, layers=1)
        >>> m(torch.zeros(2, 3, 4, dtype=torch.float64)).shape, m(torch.zeros(4)).dtype
        (torch.Size([2, 3, 6]), torch.float32)
    """

    kind = "mlp"

    def __init__(self, in_features: int, hidden: int = 128, layers: int = 2, out_features: int = 6):
        super().__init__(in_features, out_features)
        self.arch = {"kind": self.kind, "in_features": in_features, "hidden": hidden}
        self.arch.update(layers=layers, out_features=out_features)
        mods: list[nn.Module] = []
        width = in_features
        for _ in range(layers):
            mods += [nn.Linear(width, hidden), nn.SiLU()]
            width = hidden
        mods.append(nn.Linear(width, out_features))
        self.net = nn.Sequential(*mods)

    def forward(self, features: Tensor) -> Tensor:
        """Residual ``(*B, 6)`` [N; N m] from features ``(*B, F)``; dtype follows the input."""
        dtype = features.dtype if features.is_floating_point() else torch.float32
        return self._out(self.net(self._in(features))).to(dtype)


class ResidualGRU(_Normalised):
    """GRU residual model with explicit state, for drift and hysteresis.

    ``forward(features, h) -> (r_hat, h_next)`` runs one frame, so the robot can call it at its
    control rate; :meth:`forward_sequence` runs a whole sequence (training) and gives the same
    numbers as stepping frame by frame.

    Args:
        in_features: number of features F.
        hidden: GRU state size H.
        layers: stacked GRU layers L.
        out_features: 6.

    Example:
        >>> m = ResidualGRU(4, hidden=8, layers=1)
        >>> r, h = m(torch.zeros(3, 4), None)
        >>> r.shape, h.shape
        (torch.Size([3, 6]), torch.Size([3, 1, 8]))
    """

    kind = "gru"

    def __init__(self, in_features: int, hidden: int = 64, layers: int = 1, out_features: int = 6):
        super().__init__(in_features, out_features)
        self.arch = {"kind": self.kind, "in_features": in_features, "hidden": hidden}
        self.arch.update(layers=layers, out_features=out_features)
        self.hidden, self.layers = hidden, layers
        self.gru = nn.GRU(in_features, hidden, num_layers=layers, batch_first=True)
        self.head = nn.Linear(hidden + in_features, out_features)

    def initial_state(self, *batch: int, device: torch.device | str | None = None) -> Tensor:
        """Zero state ``(*batch, L, H)`` float32."""
        return torch.zeros(*batch, self.layers, self.hidden, device=device)

    def forward_sequence(self, features: Tensor, h: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Run a sequence.

        Args:
            features: ``(B, T, F)``.
            h: ``(B, L, H)`` state before the first frame, or None for zeros.

        Returns:
            ``r_hat (B, T, 6)`` in the input's dtype, ``h (B, L, H)`` float32 after the last frame.
        """
        dtype = features.dtype if features.is_floating_point() else torch.float32
        x = self._in(features)
        h0 = None if h is None else h.float().transpose(0, 1).contiguous()
        y, hn = self.gru(x, h0)
        out = self._out(self.head(torch.cat((y, x), -1)))
        return out.to(dtype), hn.transpose(0, 1)

    def forward(self, features: Tensor, h: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """One frame: ``features (*B, F)``, ``h (*B, L, H)`` -> ``(r_hat (*B, 6), h_next)``."""
        batch = features.shape[:-1]
        x = features.reshape(-1, 1, features.shape[-1])
        hh = None if h is None else h.reshape(-1, self.layers, self.hidden)
        r, hn = self.forward_sequence(x, hh)
        return r.reshape(*batch, -1), hn.reshape(*batch, self.layers, self.hidden)


_KINDS: dict[str, type[_Normalised]] = {"mlp": ResidualMLP, "gru": ResidualGRU}


def build_residual_model(arch: Mapping[str, Any]) -> ResidualMLP | ResidualGRU:
    """Construct a model from its ``arch`` dictionary (``{"kind": "mlp" | "gru", ...}``).

    Raises:
        CheckpointError: unknown kind or arguments.
    """
    arch = dict(arch)
    kind = arch.pop("kind", None)
    if kind not in _KINDS:
        raise CheckpointError(
            f"unknown residual model kind {kind!r}; expected one of {list(_KINDS)}"
        )
    try:
        return _KINDS[kind](**arch)  # type: ignore[return-value]
    except TypeError as e:
        raise CheckpointError(f"bad arch for {kind!r}: {e}") from None


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def save_residual_model(
    directory: str | Path, module: ResidualMLP | ResidualGRU, meta: Mapping[str, Any]
) -> Path:
    """Write ``weights.safetensors`` and ``checkpoint.json`` (with the weights' sha256).

    Args:
        directory: created if absent.
        module: the trained model.
        meta: ``features``, ``joint_names``, ``sensor``, ``robot_sha256``, ``data_sha256``,
            ``config``, ``metrics`` (anything JSON-serialisable); ``format``, ``arch`` and
            ``weights_sha256`` are filled in here.

    Returns:
        The directory.
    """
    from safetensors.torch import save_file

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    state = {
        k: v.detach().to("cpu", torch.float32).contiguous() for k, v in module.state_dict().items()
    }
    save_file(state, str(d / WEIGHTS_FILE), metadata={"format": CHECKPOINT_FORMAT})
    full = dict(meta)
    if len(full.get("features", [])) != module.in_features:
        raise ValueError(
            f"meta['features'] has {len(full.get('features', []))} names for"
            f" {module.in_features} inputs"
        )
    full.update(
        format=CHECKPOINT_FORMAT, arch=module.arch, weights_sha256=_sha256(d / WEIGHTS_FILE)
    )
    (d / META_FILE).write_text(json.dumps(full, indent=2, sort_keys=True) + "\n")
    return d


def load_residual_model(
    directory: str | Path,
    *,
    robot_sha256: str | None = None,
    device: torch.device | str = "cpu",
) -> tuple[ResidualMLP | ResidualGRU, dict[str, Any]]:
    """Load and verify a checkpoint directory; never unpickles.

    Checks: ``checkpoint.json`` is this format; the sha256 of ``weights.safetensors`` equals the
    recorded one; the tensor names and shapes are exactly those of the model ``arch`` builds;
    ``features`` matches the input size; optionally the robot hash matches ``robot_sha256``.

    Args:
        directory: the checkpoint directory.
        robot_sha256: ``model.urdf_sha256`` of the robot it will be used with (None: no check).
        device: where to put the module.

    Returns:
        ``(module, meta)``, the module in eval mode, meta the parsed JSON.

    Raises:
        CheckpointError: with the reason (missing file, hash mismatch, foreign format, structure).
    """
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    d = Path(directory)
    meta_path, weights_path = d / META_FILE, d / WEIGHTS_FILE
    for p in (meta_path, weights_path):
        if not p.is_file():
            raise CheckpointError(f"{d}: not a residual checkpoint ({p.name} missing)")
    try:
        meta = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{meta_path}: not valid JSON ({e})") from None
    if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
        got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise CheckpointError(
            f"{meta_path}: foreign checkpoint (format {got!r}, expected {CHECKPOINT_FORMAT!r})"
        )
    digest = _sha256(weights_path)
    if digest != meta.get("weights_sha256"):
        raise CheckpointError(
            f"{weights_path}: sha256 {digest} does not match checkpoint.json's weights_sha256"
            f" {meta.get('weights_sha256')}: the weights were modified or belong to another"
            " checkpoint"
        )
    if robot_sha256 is not None and meta.get("robot_sha256") != robot_sha256:
        raise CheckpointError(
            f"{d}: trained for robot {meta.get('robot_sha256')}, not this robot ({robot_sha256})"
        )
    module = build_residual_model(meta.get("arch", {}))
    if len(meta.get("features", [])) != module.in_features:
        raise CheckpointError(f"{d}: {len(meta.get('features', []))} feature names for arch input")
    try:
        state = load_file(str(weights_path))
    except (SafetensorError, OSError) as e:
        raise CheckpointError(f"{weights_path}: unreadable safetensors ({e})") from None
    expected = {k: tuple(v.shape) for k, v in module.state_dict().items()}
    got = {k: tuple(v.shape) for k, v in state.items()}
    if expected != got:
        diff = sorted(set(expected.items()) ^ set(got.items()))
        raise CheckpointError(f"{d}: weights do not fit the recorded arch: {diff[:6]}")
    if any(v.dtype != torch.float32 for v in state.values()):
        raise CheckpointError(f"{d}: weights must be float32")
    module.load_state_dict(state, strict=True)
    return module.to(device).eval(), meta


class ResidualCorrection:
    """Apply a learned residual to F/T readings: ``ft_corrected = ft - r_hat(features)``.

    A plain value wrapping a loaded model (not itself an ``nn.Module``). For a GRU the frames of
    one call are one time-ordered sequence and the state carries over between calls
    (:meth:`reset` starts afresh).

    Args:
        module: a :class:`ResidualMLP` or :class:`ResidualGRU`.
        meta: its checkpoint metadata (``features``, ``sensor``, ``joint_names``).

    Example:
        >>> m = ResidualMLP(3 * 2, hidden=4, layers=1)
        >>> meta = {"features": feature_names(["a", "b"]), "joint_names": ["a", "b"]}
        >>> c = ResidualCorrection(m, meta)
        >>> x = c.features(torch.zeros(5, 2), torch.zeros(5, 2), torch.zeros(5, 2))
        >>> c.correct(torch.zeros(5, 6, dtype=torch.float64), x).dtype
        torch.float64
    """

    def __init__(self, module: ResidualMLP | ResidualGRU, meta: Mapping[str, Any]) -> None:
        self.module = module.eval()
        self.meta = dict(meta)
        self.feature_names: list[str] = list(meta["features"])
        self.sensor: str = meta.get("sensor", "")
        #: where the checkpoint was loaded from ("" when built in memory)
        self.source: str = ""
        self._h: Tensor | None = None

    @property
    def recurrent(self) -> bool:
        """True for a GRU: frames must arrive in time order, the state carries over."""
        return isinstance(self.module, ResidualGRU)

    @classmethod
    def load(cls, directory: str | Path, **kwargs: Any) -> ResidualCorrection:
        """:func:`load_residual_model` then wrap (``source`` is the resolved directory)."""
        obj = cls(*load_residual_model(directory, **kwargs))
        obj.source = str(Path(directory).resolve())
        return obj

    def reset(self) -> None:
        """Forget the recurrent state."""
        self._h = None

    def features(
        self, q: Tensor, qd: Tensor, qdd: Tensor, extra: Mapping[str, Tensor] | None = None
    ) -> Tensor:
        """Assemble ``(*B, F)`` features in the checkpoint's order.

        Args:
            q: ``(*B, nv)`` in the checkpoint's ``joint_names`` order; ``qd``, ``qdd`` likewise.
            qd: ``(*B, nv)``.
            qdd: ``(*B, nv)``.
            extra: column name -> ``(*B,)`` for every extra feature (e.g. ``temperature``).

        Raises:
            KeyError: an extra feature the checkpoint needs is missing.
        """
        extra = dict(extra or {})
        joints = list(self.meta.get("joint_names", []))
        cols = []
        for name in self.feature_names:
            prefix, _, joint = name.partition(".")
            if prefix in ("q", "qd", "qdd") and joint in joints:
                src = {"q": q, "qd": qd, "qdd": qdd}[prefix]
                cols.append(src[..., joints.index(joint)])
            else:
                if name not in extra:
                    raise KeyError(f"residual model needs feature column {name!r}")
                cols.append(torch.as_tensor(extra[name], dtype=q.dtype, device=q.device))
        return torch.stack(cols, -1)

    @torch.no_grad()
    def residual(self, features: Tensor) -> Tensor:
        """``r_hat (*B, 6)`` in the features' dtype (GRU: frames in time order, state kept)."""
        if isinstance(self.module, ResidualGRU):
            flat = features.reshape(1, -1, features.shape[-1])
            r, self._h = self.module.forward_sequence(flat, self._h)
            return r.reshape(*features.shape[:-1], -1)
        return self.module(features)

    def correct(self, ft: Tensor, features: Tensor) -> Tensor:
        """``ft (*B, 6) - r_hat(features (*B, F))`` in ``ft``'s dtype and device."""
        return ft - self.residual(features.to(ft.device)).to(ft.dtype)
