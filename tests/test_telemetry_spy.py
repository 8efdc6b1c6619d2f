"""``canon spy`` for real: lcm-spy under Xvfb finds our types and shows our channels.

Marked ``multicast`` (lcm-spy joins the group of the default URL). Needs Xvfb, a Java runtime with
X11 support (the full JRE, not only the headless one) and javac (for the screenshot helper); skips
and says which is missing otherwise. The screenshot is written to ``$CANON_SCREENSHOT_DIR`` when set,
for a person to look at: lcm-spy.png, the channel table with the type names and rates, and
lcm-spy-status.png, the field view of canon.status.
"""

from __future__ import annotations

import os
import random
import re
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import lcm
import pytest
from test_telemetry_types import full_status

from telemetry import generate
from telemetry.lcmtypes.canon import event
from telemetry.publisher import EventPublisher, StatusPublisher
from telemetry.url import DEFAULT_URL

CANON = str(Path(sys.executable).parent / "canon")

SHOT_JAVA = """
import java.awt.*;
import java.awt.event.InputEvent;
import java.io.File;
import javax.imageio.ImageIO;
public class Shot {
    // Shot TABLE.png VIEW.png X Y: capture the screen (lcm-spy's channel table) into TABLE.png,
    // double-click at (X, Y) (a row of the table opens its field view), capture it into VIEW.png.
    public static void main(String[] a) throws Exception {
        Robot robot = new Robot();
        Rectangle screen = new Rectangle(Toolkit.getDefaultToolkit().getScreenSize());
        ImageIO.write(robot.createScreenCapture(screen), "png", new File(a[0]));
        robot.mouseMove(Integer.parseInt(a[2]), Integer.parseInt(a[3]));
        for (int i = 0; i < 2; i++) {
            robot.mousePress(InputEvent.BUTTON1_DOWN_MASK);
            robot.mouseRelease(InputEvent.BUTTON1_DOWN_MASK);
        }
        robot.delay(2000);
        ImageIO.write(robot.createScreenCapture(screen), "png", new File(a[1]));
    }
}
"""


def _missing() -> str | None:
    if shutil.which("Xvfb") is None:
        return "needs Xvfb (apt-get install xvfb)"
    if shutil.which("java") is None or shutil.which("javac") is None:
        return "needs java and javac (apt-get install default-jdk)"
    props = subprocess.run(["java", "-XshowSettings:properties", "-version"], capture_output=True, text=True,
                           timeout=60).stderr
    home = re.search(r"java\.home = (.+)", props)
    if home is None or not list(Path(home.group(1).strip()).glob("lib/libawt_xawt.so")):
        return "the Java runtime has no X11 support (headless only): apt-get install default-jre"
    return None


def _start_xvfb() -> tuple[subprocess.Popen[bytes], str]:
    """Xvfb on a random high display number (the machine is shared: :0 may be taken or come and go);
    ``-displayfd`` tells when it accepts connections. Another server on that number: try another."""
    for _ in range(5):
        number = random.randint(100, 999)
        read_fd, write_fd = os.pipe()
        proc = subprocess.Popen(["Xvfb", f":{number}", "-displayfd", str(write_fd), "-screen", "0",
                                 "1280x800x24", "-nolisten", "tcp"], pass_fds=(write_fd,),
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(write_fd)
        told = b""
        deadline = time.monotonic() + 15
        try:
            # read up to the newline: Xvfb writes the number and the newline separately, and fails
            # ("Cannot write display number") if the pipe is closed in between
            while not told.endswith(b"\n") and time.monotonic() < deadline:
                ready, _, _ = select.select([read_fd], [], [], max(0.0, deadline - time.monotonic()))
                chunk = os.read(read_fd, 32) if ready else b""
                if not chunk:
                    break
                told += chunk
        finally:
            os.close(read_fd)
        if told.strip() == str(number).encode() and proc.poll() is None:
            return proc, f":{number}"
        _stop(proc)
    pytest.fail("Xvfb did not start on any of 5 display numbers")


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@pytest.mark.multicast
@pytest.mark.slow
@pytest.mark.skipif(_missing() is not None, reason=str(_missing()))
def test_lcm_spy_shows_our_channels_with_their_types(tmp_path: Path) -> None:
    (tmp_path / "Shot.java").write_text(SHOT_JAVA)
    javac = subprocess.run(["javac", "-nowarn", "-d", str(tmp_path), str(tmp_path / "Shot.java")],
                           capture_output=True, text=True, timeout=120)
    assert javac.returncode == 0, javac.stderr

    xvfb, display = _start_xvfb()
    spy_out = tmp_path / "spy.out"
    lc = lcm.LCM(DEFAULT_URL)
    spy = None
    try:
        with StatusPublisher(lc, 50) as sp, EventPublisher(lc) as ep, spy_out.open("wb") as out:
            sp.update(full_status())
            env = dict(os.environ, DISPLAY=display)
            spy = subprocess.Popen([CANON, "spy"], env=env, stdout=out, stderr=subprocess.STDOUT)
            deadline = time.monotonic() + 30
            while "plugins" not in spy_out.read_text(errors="replace") and time.monotonic() < deadline:
                assert spy.poll() is None, spy_out.read_text(errors="replace")
                ep.emit(event.INFO, "waiting for lcm-spy", source="test")
                time.sleep(0.2)
            for _ in range(15):  # let rates settle; events keep coming
                ep.emit(event.INFO, "tick", source="test")
                time.sleep(0.2)
            pngs = [tmp_path / "lcm-spy.png", tmp_path / "lcm-spy-status.png"]
            # rows are sorted by channel: CANON_EVENT first, CANON_STATUS second
            shot = subprocess.run(["java", "-cp", str(tmp_path), "Shot", *map(str, pngs), "60", "43"],
                                  env=env, capture_output=True, text=True, timeout=60)
            assert shot.returncode == 0, shot.stderr
            assert spy.poll() is None, "lcm-spy ended early:\n" + spy_out.read_text(errors="replace")
    finally:
        if spy is not None:
            _stop(spy)
        _stop(xvfb)

    text = spy_out.read_text(errors="replace")
    found = re.search(r"Found (\d+) LCM types", text)
    assert found, text
    n_structs = sum(len(re.findall(r"^struct ", f.read_text(), re.M)) for f in generate.lcm_files())
    assert int(found.group(1)) >= n_structs  # our jar is on lcm-spy's CLASSPATH
    if os.environ.get("CANON_SCREENSHOT_DIR"):
        for png in pngs:
            shutil.copy(png, Path(os.environ["CANON_SCREENSHOT_DIR"]) / png.name)

    from matplotlib import image

    table, view = (image.imread(png) for png in pngs)
    assert table.shape[:2] == (800, 1280)
    assert table.std() > 0.05, "the screenshot is blank"
    assert abs(view - table).mean() > 0.01, "double-clicking the CANON_STATUS row opened no field view"
