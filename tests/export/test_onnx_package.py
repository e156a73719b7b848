"""The deployment wing's shape: its imports, re-exports, one input table, robot identity in graphs.

``torchcontact/onnx/`` imports nothing from the log pipeline, the training or the drivers, and
nothing below it imports it; no file there is over 900 lines; ``torchcontact.export`` and
``torchcontact.runtime`` re-export its public names; the runtime takes one inputs value (old
spellings accepted); graphs record the robot's identity, so a reformatted URDF still fits and a
10 g mass change does not.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from export_scenes import scene

import torchcontact as tc
from torchcontact.errors import InputError, ModelMismatchError

ROOT = Path(tc.__file__).parent
WING = ROOT / "onnx"


def _imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_the_wing_imports_no_pipeline_training_or_drivers_and_is_not_imported_below():
    for path in WING.rglob("*.py"):
        bad = {m for m in _imports(path)
               if m.startswith(("torchcontact.logs", "torchcontact.drivers", "training"))}  # fmt: skip
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"
        assert len(path.read_text().splitlines()) <= 900, path
    above = {"export.py", "runtime.py", "cli.py"}  # the re-exports and the application layer
    for path in ROOT.rglob("*.py"):
        rel = path.relative_to(ROOT)
        if rel.parts[0] in ("onnx", "drivers", "apps") or rel.name in above:
            continue
        bad = {m for m in _imports(path) if m.startswith("torchcontact.onnx")}
        assert not bad, f"{rel} (below the wing) imports {bad}"


def test_public_names_are_re_exported():
    import torchcontact.export as ex
    import torchcontact.onnx.export as oex
    import torchcontact.onnx.runtime as ort_
    import torchcontact.runtime as rt

    for name in ex.__all__:
        assert getattr(ex, name) is getattr(oex, name), name
    for name in rt.__all__:
        assert getattr(rt, name) is getattr(ort_, name), name
    assert ex.export_estimator is tc.onnx.export_estimator
    assert rt.EstimatorRuntime is tc.onnx.EstimatorRuntime


def test_the_input_table_in_the_docs():
    """``docs/names.md`` lists every input of :data:`torchcontact.onnx.format.INPUTS`."""
    from torchcontact.onnx.format import INPUTS

    doc = (ROOT.parent / "docs" / "names.md").read_text()
    rows = [r for r in doc.splitlines() if r.startswith("| `")]
    names = [re.match(r"\| `([a-z_]+)`", r).group(1) for r in rows]
    assert names == [i.name for i in INPUTS]
    for i, row in zip(INPUTS, rows, strict=True):
        for alias in i.aliases:
            assert f"`{alias}`" in row, (i.name, alias)


def test_one_inputs_value_and_the_old_spellings(exports):
    from torchcontact.runtime import Inputs

    rt = exports.runtime("panda")
    x = scene("panda", 1, seed=8)
    f = {k: v[0] for k, v in x.items() if k != "truth"}
    want = rt.step(Inputs(**f))
    by_map = rt.step(f)
    old = dict(f)
    old["tau_meas"], old["pos"], old["ft_covariance"] = (
        old.pop("tau_measured"), old.pop("positions"), old.pop("ft_cov"))  # fmt: skip
    by_alias = rt.step(old)
    legacy = rt.step(f["q"], f["qd"], f["qdd"], f["ft"], f["positions"],
                     **{k: v for k, v in f.items() if k not in ("q", "qd", "qdd", "ft", "positions")})  # fmt: skip
    for out in (by_map, by_alias, legacy):
        np.testing.assert_array_equal(out["force"], want["force"])
        assert out["status"] == want["status"] == 0
    batch = rt.run(Inputs(**{k: v for k, v in x.items() if k != "truth"}))
    np.testing.assert_allclose(batch["force"][0], want["force"], atol=1e-9)
    with pytest.raises(InputError, match="unknown input 'offset'"):
        rt.step({**f, "offset": np.zeros(6)})


def test_graphs_record_the_robot_identity(tmp_path):
    """A reformatted URDF still fits the graph; a 10 g mass change is refused, named."""
    from torchcontact.export import export_estimator
    from torchcontact.runtime import EstimatorRuntime

    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    path = tmp_path / "arm.onnx"
    export_estimator(model, None, ["hand_skin"], ["force"], path, dtype=torch.float64,
                     step_graph=False)  # fmt: skip
    text = Path(tc.robots.tcarm_path()).read_text()
    same = tmp_path / "reformatted.urdf"
    same.write_text(text.replace("<robot", "<!-- kept -->\n<robot", 1).replace("  ", "    "))
    EstimatorRuntime(path, robot=same)
    m = re.search(r'<link name="hand">.*?<mass value="([0-9.]+)"', text, re.S)
    heavier = text[: m.start(1)] + f"{float(m.group(1)) + 0.01:g}" + text[m.end(1) :]
    (tmp_path / "heavier.urdf").write_text(heavier)
    with pytest.raises(ModelMismatchError, match=r"link hand: mass \S+ vs \S+ kg"):
        EstimatorRuntime(path, robot=tmp_path / "heavier.urdf")
    ident = tc.RobotModel.from_urdf(same).identity.sha256
    EstimatorRuntime(path, expect_robot_sha256=ident)


def test_constrained_graph_holds_one_iteration(tmp_path):
    """The cone iterations are one ONNX Loop: the graph does not grow with the budget."""
    from torchcontact.export import export_estimator

    model = tc.RobotModel.from_urdf(tc.robots.tcarm_path())
    sizes = {}
    for it in (3, 30):
        p = tmp_path / f"c{it}.onnx"
        export_estimator(model, None, ["hand_skin"], ["force"], p, dtype=torch.float64,
                         constraints=tc.FrictionCones(it))  # fmt: skip
        g = onnx.load(str(p)).graph
        assert [n.op_type for n in g.node].count("Loop") == 1
        sizes[it] = len(g.node)
    assert sizes[3] == sizes[30]
