"""gcode_canon: RS274/NGC (LinuxCNC dialect) text in, canonical machining commands out.

Pure Python with no fieldbus imports: the lowest layer of canon.
"""

from gcode_canon.commands import AXES, Canon, Pose
from gcode_canon.errors import GCodeError

__all__ = ["AXES", "Canon", "GCodeError", "Pose"]
