"""Small robot descriptions written by this project, for examples, tests and first runs."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["TCARM_SKIN_FRAMES", "pendulum_urdf", "tcarm_path"]

#: Skin patch frames of the bundled arm (fixed frames on its links; contacts lie on them).
TCARM_SKIN_FRAMES = ("upper_arm_skin", "forearm_skin", "hand_skin")


def tcarm_path() -> Path:
    """Path of the bundled robot ``tcarm``: a 7-joint arm on a base F/T sensor (``base_ft``).

    Written by this project for examples, tests and first runs (not a real product). Skin
    patches are the fixed frames :data:`TCARM_SKIN_FRAMES`; ``tool`` is the flange.

    Example:
        >>> import torchcontact as tc
        >>> tc.RobotModel.from_urdf(tc.robots.tcarm_path()).joint_names[:2]
        ('shoulder_yaw', 'shoulder_pitch')
    """
    return Path(str(resources.files("torchcontact") / "data" / "robots" / "tcarm.urdf"))


def pendulum_urdf(length: float = 1.0, mass: float = 1.0) -> str:
    """URDF text of a pendulum: a uniform rod on a revolute joint about y, horizontal at q = 0.

    Args:
        length: rod length, m (the rod lies along +x from the joint).
        mass: rod mass, kg.

    Returns:
        The URDF XML as a string.

    Example:
        >>> "<robot" in pendulum_urdf()
        True
    """
    i_end = mass * length**2 / 12.0
    return f"""<?xml version="1.0"?>
<robot name="pendulum">
  <link name="base"/>
  <link name="rod">
    <inertial>
      <origin xyz="{length / 2} 0 0" rpy="0 0 0"/>
      <mass value="{mass}"/>
      <inertia ixx="1e-6" ixy="0" ixz="0" iyy="{i_end}" iyz="0" izz="{i_end}"/>
    </inertial>
  </link>
  <joint name="hinge" type="revolute">
    <parent link="base"/>
    <child link="rod"/>
    <axis xyz="0 -1 0"/>
    <limit lower="-3.14" upper="3.14" effort="100" velocity="10"/>
  </joint>
</robot>
"""
