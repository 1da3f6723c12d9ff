"""The robot and the images as the command line names them (``--robot``, ``--image``), made
into a rig (``core.acquisition.rig``): ``sim`` is the twin's UR3 in-process and its scanner,
``ur:HOST`` a UR controller (or ``probecal ursim``) through ur_rtde, ``igtl:HOST:PORT``,
``video:DEVICE_OR_FILE`` and ``replay:SESSION_DIR`` live image streams."""

from __future__ import annotations

from probecal.core.acquisition.igtlsource import IgtlSource
from probecal.core.acquisition.imagesource import ImageSource
from probecal.core.acquisition.rig import Rig, assemble_rig
from probecal.core.acquisition.videosource import ReplaySource, VideoSource
from probecal.core.errors import InputError
from probecal.core.geometry.probe import Probe
from probecal.core.robot.contract import HOME_JOINTS, Robot
from probecal.core.robot.safety import Workspace
from probecal.core.robot.simulated import SimulatedRobot


def make_rig(robot: str = "sim", image: str = "sim", seed: int = 0, time_scale: float = 0.25,
             workspace: Workspace | None = None, latency_s: float = 0.0,
             spacing_mm: tuple[float, float] | None = None, start_depth_mm: float | None = None,
             probe: Probe | None = None) -> Rig:
    """A rig from ``--robot``, ``--image``, ``--spacing`` (sx, sy mm/px), ``--start-depth-mm``
    (mm) and ``--probe`` (the twin's probe; None: its default); ``time_scale`` is the simulated
    robot's wall seconds per robot second. InputError on a bad name, or on a start depth for
    the twin's images, which start at its probe's face."""
    if image == "sim" and start_depth_mm is not None:
        raise InputError(None, "--start-depth-mm is a live scanner's: the simulated scanner's images start at its "
                               "probe's face (probecal simulate --start-depth-mm renders another preset)")
    arm, name = parse_robot_spec(robot, seed, time_scale)
    return assemble_rig(arm, name, parse_image_spec(image), seed, workspace, latency_s, spacing_mm,
                        start_depth_mm, probe, specs=(robot, image))


def parse_robot_spec(text: str, seed: int = 0, time_scale: float = 0.25) -> tuple[Robot, str]:
    """The robot ``--robot`` names, and its name in messages: sim (the twin's UR3, its
    repeatability drawn from ``seed``, ``time_scale`` wall s per robot s) or ur:HOST."""
    if text == "sim":
        return SimulatedRobot(home_joints=HOME_JOINTS, seed=seed, time_scale=time_scale), "the simulated UR3"
    if text.startswith("ur:") and len(text) > 3:
        from probecal.core.robot.urprocess import URRobotProcess  # the UR backend only for a real robot

        host = text[3:]
        return URRobotProcess(host), f"the UR controller at {host}"
    raise InputError(None, f"--robot {text!r}: expected sim or ur:HOST")


def parse_image_spec(text: str) -> ImageSource | None:
    """The source ``--image`` names: igtl:HOST:PORT, video:DEVICE_OR_FILE or replay:SESSION_DIR;
    None for "sim" (the twin's scanner)."""
    if text == "sim":
        return None
    kind, _, rest = text.partition(":")
    if kind == "igtl":
        host, _, port = rest.rpartition(":")
        if host and port.isdigit() and 0 < int(port) < 65536:
            return IgtlSource(host, int(port))
    elif kind == "video" and rest:
        return VideoSource(rest)
    elif kind == "replay" and rest:
        return ReplaySource(rest)
    raise InputError(
        None, f"bad image source {text!r}: expected sim, igtl:HOST:PORT, video:DEVICE_OR_FILE or replay:SESSION_DIR"
    )
