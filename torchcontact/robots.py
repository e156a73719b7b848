"""Small robot descriptions written by this project, for examples, tests and first runs."""

from __future__ import annotations

__all__ = ["pendulum_urdf"]


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
