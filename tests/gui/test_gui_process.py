"""``scara-gui`` as a process: Ctrl-C stops it cleanly, even when it was started as a script's
``cmd &`` starts it (SIGINT ignored); no browser."""

from __future__ import annotations

from pathlib import Path

from gui_stack import start_gui
from mcap.writer import Writer
from support import SIGINT_IGNORED, Processes


def test_ctrl_c_stops_the_server_with_exit_0_and_no_traceback(
    processes: Processes, tmp_path: Path
) -> None:
    recording = tmp_path / "empty.mcap"  # a whole recording of nothing: no robot needed
    with recording.open("wb") as stream:
        writer = Writer(stream)
        writer.start()
        writer.finish()
    start_gui(processes, str(recording), name="gui", prefix=SIGINT_IGNORED)
    gui = processes.started[-1]
    assert gui.interrupt() == 0, gui.output()
    output = gui.output()
    assert "scara-gui: stopped" in output and "Traceback" not in output, output
