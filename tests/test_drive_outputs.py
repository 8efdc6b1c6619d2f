"""The drives' digital outputs (CiA 402 0x60FE) as points of the I/O map: the master writes them by SDO
on its own thread (fieldbus.canopen.master_outputs), the simulated drive keeps them, and an I/O map
function bound to one switches it from the program. docs/wiring.md."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from canopen_helpers import Rig, make_config
from motion_process_helpers import group, own_mode
from test_run_from_line import wait_for

from fieldbus.canopen.drive_sim import SimDrive
from fieldbus.canopen.master import CanopenError
from motiond.config import load_machine
from motiond.runtime import Machine
from motiond.states import State

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "canon.toml"
MIST = 17  # drive z's 0x60FE bit the tests bind coolant_mist to


def test_the_master_writes_a_drive_output_bit_and_the_drive_keeps_it() -> None:
    rig = Rig(make_config(2))
    try:
        rig.master.boot()
        t0 = time.monotonic()
        done = rig.master.set_output(1, 16, True).result(5.0)
        assert done >= t0
        assert rig.sim(2).digital_outputs() == 1 << 16
        rig.master.set_output(1, 17, True).result(5.0)
        rig.master.set_output(1, 16, False).result(5.0)
        assert rig.sim(2).digital_outputs() == 1 << 17  # the other bits as commanded
        assert rig.sim(1).digital_outputs() == 0
        assert rig.master.outputs() == (0, 1 << 17)
        rig.master.boot()  # an NMT reset: the master writes the commanded word again
        assert rig.sim(2).digital_outputs() == 1 << 17
    finally:
        rig.close()


def test_a_drive_without_0x60fe_fails_the_write_naming_node_and_object() -> None:
    cfg = make_config(1)
    rig = Rig(cfg, sims=[SimDrive(1, absent_objects={0x60FE})])
    try:
        rig.master.boot()
        exc = rig.master.set_output(0, 3, True).exception(5.0)
        assert isinstance(exc, CanopenError)
        assert "node 1 (axis x)" in str(exc) and "0x60FE" in str(exc) and "aborted by the drive" in str(exc)
    finally:
        rig.close()


@pytest.fixture
def machine(tmp_path: Path) -> Iterator[Machine]:
    text = EXAMPLE.read_text()
    old = 'coolant_mist = { device = "io", coil = 12 }'
    assert old in text
    f = tmp_path / "m.toml"
    # the motion pinned to a thread: these tests read the simulated drive's outputs in this process
    # (the own-mode path is test_a_drive_output_is_written_from_the_task_with_the_motion_in_its_own_process)
    f.write_text(text.replace(old, f'coolant_mist = {{ drive = "z", bit = {MIST} }}')
                 + '\n[motion]\nprocess = "thread"\n')
    with started(f, tmp_path) as m:
        yield m


@contextlib.contextmanager
def started(config: Path, tmp_path: Path) -> Iterator[Machine]:
    """The machine of file ``config``, started and enabled (its simulated module on a free port)."""
    m = Machine(load_machine(str(config)), lc=None, var_file=tmp_path / "p.var", modbus_port=0)
    m.start()
    try:
        m.bring_up()
        yield m
    finally:
        m.shutdown()


def _status(m: Machine) -> dict[str, float]:
    s = m.status()
    return dict(zip(s.io_function_names, s.io_function_values, strict=True))


def _mist_on(machine: Machine, tmp_path: Path, text: str) -> tuple[SimDrive, object]:
    """Run ``text`` (M7 on line 3) and wait until drive z's bit is on: the drive and the job."""
    z = machine.sim_drives[machine.names.index("z")]
    prog = tmp_path / "p.ngc"
    prog.write_text(text)
    job = machine.run(prog)
    wait_for(lambda: z.digital_outputs() == 1 << MIST, "drive z 0x60FE bit 17 on after M7")
    return z, job


def test_m7_m9_switch_a_drive_output_bit(machine: Machine, tmp_path: Path) -> None:
    z, job = _mist_on(machine, tmp_path, "%\nG21 G90 G94\nM7\nG4 P1.0\nG1 X2 F3000\nM9\nM2\n%\n")
    assert _status(machine)["coolant_mist"] == 1.0  # in the LCM status as the other functions
    result = machine.wait_job(job, 30.0)
    assert result is not None and result.ok, result.error if result else "timeout"
    wait_for(lambda: z.digital_outputs() == 0, "the bit off after M9")  # written on the master's thread
    names = [(o.name, o.value, o.line) for o in result.outputs if o.kind == "function"]
    assert names == [("coolant_mist", 1.0, 3), ("coolant_mist", 0.0, 6)]


def test_estop_drops_a_drive_output_bit(machine: Machine, tmp_path: Path) -> None:
    z, job = _mist_on(machine, tmp_path, "%\nG21 G90 G94\nM7\nG4 P5.0\nM2\n%\n")
    machine.estop("test")
    wait_for(lambda: machine.states.state is State.ESTOP, "ESTOP")
    wait_for(lambda: z.digital_outputs() == 0, "the drive output off on E-stop")
    machine.wait_job(job, 10.0)


@pytest.mark.multicast
@pytest.mark.timeout(180)
def test_a_drive_output_is_written_from_the_task_with_the_motion_in_its_own_process(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """With the motion in a process of its own the task's I/O side asks the motion process, whose master
    writes 0x60FE; the answer comes when the drive confirmed the SDO write, and the caller never waits
    for it (``MotionProxy.drive_output``). Checked on the bus by a listener that sends nothing: the
    master's SDO download of 0x60FE:01 with the word, and the drive's confirmation (a second SDO client
    on the node would take the master's answers: a reading bench made the master's write time out)."""
    import can

    from fieldbus.canopen.config import CanBusConfig

    text = EXAMPLE.read_text().replace('coolant_mist = { device = "io", coil = 12 }',
                                       f'coolant_mist = {{ drive = "z", bit = {MIST} }}')
    f = tmp_path / "own.toml"
    f.write_text(own_mode(text))
    with started(f, tmp_path) as m:
        assert m.motion_mode == "own" and not m.sim_drives
        z = m.names.index("z")
        node = 3
        tap = can.Bus(**CanBusConfig("udp_multicast", group()).bus_kwargs())
        frames: list[tuple[int, bytes]] = []
        notifier = can.Notifier(tap, [lambda msg: frames.append((msg.arbitration_id, bytes(msg.data)))])

        def written(word: int, since: int) -> bool:
            """The master wrote ``word`` to 0x60FE:01 and the drive confirmed it, after frame ``since``."""
            seen = frames[since:]
            want = b"\x23\xfe\x60\x01" + word.to_bytes(4, "little")  # expedited download, 4 bytes
            asked = [i for i, (cob, data) in enumerate(seen) if cob == 0x600 + node and data == want]
            return bool(asked) and any(cob == 0x580 + node and data[:4] == b"\x60\xfe\x60\x01"
                                       for cob, data in seen[asked[0]:])

        try:
            t0 = time.monotonic()
            n0 = len(frames)
            fut = m.motion.drive_output(z, MIST, True)
            assert fut.result(10.0) >= t0 - 1.0  # the master's time of the write (its clock: monotonic)
            wait_for(lambda: written(1 << MIST, n0), "the write of bit 17 and its confirmation on the bus")
            n0 = len(frames)
            m.motion.drive_output(z, MIST, False).result(10.0)
            wait_for(lambda: written(0, n0), "the write of 0 and its confirmation on the bus")
            with pytest.raises(ValueError, match="0x60FE bit 40"):  # refused by the motion process
                m.motion.drive_output(z, 40, True).result(10.0)
            # and from a program: M7 / M9 switch it with nothing left unwritten
            prog = tmp_path / "p.ngc"
            prog.write_text("%\nG21 G90 G94\nM7\nG4 P0.5\nM9\nG4 P0.5\nM2\n%\n")
            n0 = len(frames)
            result = m.wait_job(m.run(prog), 60.0)
            assert result is not None and result.ok, result.error if result else "timeout"
            names = [(o.name, o.value, o.line) for o in result.outputs if o.kind == "function"]
            assert names == [("coolant_mist", 1.0, 3), ("coolant_mist", 0.0, 5)]
            assert not [r for r in caplog.records if "not written" in r.getMessage()]
            wait_for(lambda: written(1 << MIST, n0), "M7's write on the bus")
        finally:
            notifier.stop()
            tap.shutdown()
