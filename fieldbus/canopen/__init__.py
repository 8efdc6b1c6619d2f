"""CANopen side of ``fieldbus``: a CiA 402 master streaming CSP setpoints, and simulated drives.

``config`` holds the typed configuration, ``cia402`` the drive state machine shared by master and
simulator, ``busload`` the bus budget, ``master`` the master, ``clock`` the absolute-deadline periodic
runner, ``touch_probe`` a drive's touch probe as the probe input for G38.x, ``drive_sim`` one
simulated drive (its concerns in ``drive_sim_*``) and ``sim_process`` several of them on one bus.
"""

from pathlib import Path

#: The EDS of the simulated drive, used when a drive's configuration names none.
SHIPPED_EDS = Path(__file__).resolve().parent / "eds" / "cia402_drive.eds"
