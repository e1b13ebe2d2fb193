"""python-can's curses ``can.viewer`` as an outside client of the plant over CAN-over-Zenoh,
driven in a real terminal (tmux)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time

import pytest
from conftest import free_port


@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed")
@pytest.mark.timeout(60)
def test_can_viewer_shows_the_plants_frames() -> None:
    port = free_port()
    session = f"viewer-{port}"
    viewer = f"{sys.executable} -m can.viewer -i zenoh -c scara --bus-kwargs port={port}"
    subprocess.run(
        ["tmux", "new-session", "-d", "-s", session, "-x", "160", "-y", "40", viewer], check=True
    )
    try:
        time.sleep(2.0)
        plant = [sys.executable, "-m", "plant_sim.node", "--duration", "3"]
        subprocess.run(
            [*plant, "--bus-option", f"port={port}"], check=True, timeout=30, capture_output=True
        )
        screen = subprocess.run(
            ["tmux", "capture-pane", "-t", session, "-p"], capture_output=True, text=True
        ).stdout
    finally:
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True)
    rows = {line.split()[3]: line.split() for line in screen.splitlines() if "0x" in line}
    assert {"0x110", "0x111", "0x112", "0x701"} <= set(rows), screen
    assert int(rows["0x110"][0]) > 1000  # about 500 Hz for 3 s, idle-state frames
    assert rows["0x110"][4] == "7"  # DLC of JointState1
