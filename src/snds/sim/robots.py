"""The simulated arms: where their models come from and where a task is placed for them.

Each robot is one frozen record: its URDF source, the link that is the end effector, a rest
pose (the null-space posture the controller leans towards) and a horizontal work plane in
front of it, on which a 2-D task is drawn. :data:`ROBOTS` maps the names the CLI accepts to
these records.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from snds.errors import SimulationError

__all__ = ["ROBOTS", "Robot", "get_robot"]


@dataclass(frozen=True, kw_only=True)
class Robot:
    """A fixed-base arm and the place of a task in its workspace.

    Attributes:
        name: The name the CLI accepts.
        source: Where the URDF comes from: ``"pybullet_data"`` or ``"example-robot-data"``.
        urdf: Path of the URDF inside that source.
        end_effector: Name of the end-effector link.
        tool: The controlled point in that link's frame, metres (a tool tip below a bare
            flange, so that the path is drawn where a pen would be, not inside the wrist).
        rest_pose: Joint positions (radians) of the controlled joints at rest, elbow up and
            the tool pointing down; the start of every run and the controller's null-space
            posture.
        plane_origin: Where the task's target lands, in metres in the world frame.
        plane_axes: World directions of the task's first two coordinates (orthonormal).
        reach: Radius (metres) of the part of the plane a task may use; the default scale
            fits the demonstrations' extent into it.
        camera: (distance in metres, yaw and pitch in degrees) of the camera of the rendered
            frames, which looks at a point between the base and the plane origin.
    """

    name: str
    source: str
    urdf: str
    end_effector: str
    tool: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rest_pose: tuple[float, ...]
    plane_origin: tuple[float, float, float]
    plane_axes: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.0, 1.0, 0.0),
        (-1.0, 0.0, 0.0),
    )
    reach: float = 0.2
    camera: tuple[float, float, float] = (1.3, 60.0, -50.0)

    def urdf_path(self, scratch: Path) -> Path:
        """The URDF file to load, resolved from its source.

        Arguments:
            scratch: A folder for a rewritten copy, when the file names its meshes through a
                ``package://`` address that PyBullet cannot resolve.
        """
        return _SOURCES[self.source](self.urdf, Path(scratch))


def _pybullet_data(urdf: str, scratch: Path) -> Path:
    try:
        import pybullet_data
    except ImportError as error:
        raise SimulationError("simulation needs PyBullet: pip install 'snds[sim]'") from error
    return Path(pybullet_data.getDataPath()) / urdf


def _example_robot_data(urdf: str, scratch: Path) -> Path:
    try:
        share = Path(
            metadata.distribution("example-robot-data").locate_file(
                "cmeel.prefix/share/example-robot-data"
            )
        )
    except metadata.PackageNotFoundError as error:
        raise SimulationError(
            "the Jaco2 model needs example-robot-data: pip install 'snds[jaco2]'"
        ) from error
    source = share / urdf
    if not source.is_file():
        raise SimulationError(f"{source}: missing from example-robot-data")
    # The file names its meshes as package://example-robot-data/...; PyBullet has no package
    # resolver, so a copy with absolute paths is loaded instead.
    text = re.sub(r"package://example-robot-data/", f"{share.as_posix()}/", source.read_text())
    copy = Path(scratch) / source.name
    copy.write_text(text)
    return copy


_SOURCES = {"pybullet_data": _pybullet_data, "example-robot-data": _example_robot_data}

#: The arms ``snds simulate --robot`` accepts.
ROBOTS: dict[str, Robot] = {
    "iiwa": Robot(
        name="iiwa",
        source="pybullet_data",
        urdf="kuka_iiwa/model.urdf",
        end_effector="lbr_iiwa_link_7",
        tool=(0.0, 0.0, 0.1),
        rest_pose=(0.0, 0.5, 0.0, -1.4, 0.0, 1.2, 0.0),
        plane_origin=(0.55, 0.0, 0.35),
    ),
    "panda": Robot(
        name="panda",
        source="pybullet_data",
        urdf="franka_panda/panda.urdf",
        end_effector="panda_grasptarget",
        rest_pose=(0.0, -0.2, 0.0, -2.2, 0.0, 2.0, 0.785),
        plane_origin=(0.5, 0.0, 0.3),
        camera=(1.25, 60.0, -50.0),
    ),
    "jaco2": Robot(
        name="jaco2",
        source="example-robot-data",
        urdf="robots/kinova_description/robots/kinova.urdf",
        end_effector="j2s6s200_end_effector",
        rest_pose=(-0.585, 3.791, 0.892, -1.376, 1.618, -2.904),
        plane_origin=(0.0, -0.45, 0.3),
        plane_axes=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
        reach=0.15,
        camera=(1.05, -30.0, -50.0),
    ),
}


def get_robot(name: str) -> Robot:
    """The robot of that name, or a :class:`SimulationError` listing the choices."""
    try:
        return ROBOTS[name.lower()]
    except KeyError:
        raise SimulationError(f"unknown robot {name!r}; choose from {list(ROBOTS)}") from None
