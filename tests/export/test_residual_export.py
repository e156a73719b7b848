"""Generic residual-model export: an MLP and a GRU cell defined here, dynamic batch, parity."""

from __future__ import annotations

import onnx
import pytest
import torch
from torch import nn

from torchcontact.export import check_parity, export_residual


class MLP(nn.Module):
    def __init__(self, f=12):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(f, 32), nn.Tanh(), nn.Linear(32, 6))

    def forward(self, x):
        return self.net(x)


class GRUResidual(nn.Module):
    def __init__(self, f=12, h=16):
        super().__init__()
        self.cell, self.head = nn.GRUCell(f, h), nn.Linear(h, 6)

    def forward(self, x, h):
        h = self.cell(x, h)
        return self.head(h), h


@pytest.mark.parametrize("recurrent", [False, True])
def test_residual_export_parity(tmp_path, recurrent):
    torch.manual_seed(0)
    mod = GRUResidual() if recurrent else MLP()
    path = tmp_path / "res.onnx"
    ex = torch.randn(3, 12)
    state = torch.randn(3, 16) if recurrent else None
    meta = export_residual(mod, ex, path, {"sensor": "base_ft", "features": 12}, 17, state)
    props = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert props["sensor"] == "base_ft" and props["recurrent"] == str(recurrent).lower()
    assert props == meta and len(props["sha256_weights"]) == 64
    m = onnx.load(str(path))
    assert m.graph.initializer  # weights inside the file
    assert [i.name for i in m.graph.input] == (["features", "h_in"] if recurrent else ["features"])
    for n in (1, 2, 7, 1024):
        ins = [torch.randn(n, 12)] + ([torch.randn(n, 16)] if recurrent else [])
        assert check_parity(mod, path, ins, atol=1e-5) <= 1e-5


def test_check_parity_detects_a_difference(tmp_path):
    mod = MLP()
    path = tmp_path / "res.onnx"
    export_residual(mod, torch.randn(2, 12), path)
    with torch.no_grad():
        mod.net[2].bias += 1e-3
    with pytest.raises(AssertionError, match="differs"):
        check_parity(mod, path, torch.randn(4, 12))
