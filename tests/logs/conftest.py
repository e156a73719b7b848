"""Fixtures: small simulated logs of the bundled tcarm (made by torchcontact.simulation.simulate,
seeded, so every run writes the same bytes; nothing binary is checked in)."""

from __future__ import annotations

import pytest

pytest.importorskip("pyarrow")

import torch  # noqa: E402

import torchcontact as tc  # noqa: E402

# as the CLI does (--threads 1): the estimator's small index_add kernels are ~2000x slower with
# two intra-op threads on a 2-core machine
torch.set_num_threads(1)
from torchcontact.logs import write_simulated_log  # noqa: E402


@pytest.fixture(scope="session")
def model():
    return tc.RobotModel.from_urdf(tc.robots.tcarm_path())


@pytest.fixture(scope="session")
def sim_log(model, tmp_path_factory):
    """600 frames with qd/qdd, one or two force contacts per contact frame."""
    return write_simulated_log(model, 600, tmp_path_factory.mktemp("sim") / "log.parquet", seed=3)


@pytest.fixture(scope="session")
def sim_log_q_only(model, tmp_path_factory):
    """The same trajectory without qd/qdd (the pipeline derives them)."""
    path = tmp_path_factory.mktemp("simq") / "log.parquet"
    return write_simulated_log(model, 600, path, seed=3, derivatives=False)


@pytest.fixture(scope="session")
def changing(sim_log, tmp_path_factory):
    """The simulated log with its contact set changed mid-file: until frame 300 only the records
    on forearm_skin, from there on every record plus a second copy of each hand_skin one."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    tab = pq.read_table(sim_log)
    rows = tab["contacts"].to_pylist()
    for i, row in enumerate(rows):
        if i < 300:
            rows[i] = [c for c in row if c["link"] == "forearm_skin"]
        else:
            rows[i] = row + [dict(c) for c in row if c["link"] == "hand_skin"]
    contacts = pa.array(rows, tab.schema.field("contacts").type)
    path = tmp_path_factory.mktemp("changing") / "log.parquet"
    pq.write_table(tab.set_column(tab.schema.get_field_index("contacts"), "contacts", contacts),
                   path)  # fmt: skip
    return path
