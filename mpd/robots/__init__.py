"""Point mass, planar n-link arms and the Franka Panda as batched torch kinematic chains."""

from mpd.robots.chain import KinematicChain, Kinematics
from mpd.robots.robot import Robot, get_robot, pk_serial_chain
from mpd.robots.spec import RobotSpec, load_robot_spec, robot_files

__all__ = [
    "Kinematics",
    "KinematicChain",
    "Robot",
    "RobotSpec",
    "get_robot",
    "load_robot_spec",
    "pk_serial_chain",
    "robot_files",
]
