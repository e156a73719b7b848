import pytest
import torch

import torchcontact as tc


@pytest.fixture(scope="session", autouse=True)
def _one_thread():
    # tiny models: one thread avoids oversubscription on small CI machines
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def arm():
    return tc.RobotModel.from_urdf(tc.robots.tcarm_path())
