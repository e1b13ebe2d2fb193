"""What the GUI's tests share beside their fixtures (``conftest.py``): a ``scara-gui`` server
started as a process, and the robot the pages look at. (A module of its own: ``from conftest
import`` would find whichever test folder's ``conftest`` was imported first.)"""

from __future__ import annotations

import ssl
import sys
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh
from support import ROOT, Processes, free_port, wait_until

sys.path.insert(0, str(ROOT / "tests" / "bridge"))  # the bridge tests' robot as a service
from robot_stack import START, Stack


def start_gui(
    processes: Processes,
    *args: str,
    name: str,
    prefix: Sequence[str] = (),
    https: Path | None = None,
) -> str:
    """``scara-gui ARGS`` on a free port; its URL once it serves the page. With ``https``
    (a ``scara-certs`` folder) it serves https with that set's server certificate, checked
    against the set's CA."""
    port = free_port()
    scheme, context = "http", None
    if https is not None:
        args = (*args, "--https-cert", str(https / "server.pem"))
        args = (*args, "--https-key", str(https / "server-key.pem"))
        scheme, context = "https", ssl.create_default_context(cafile=https / "ca.pem")
    gui = processes.start("gui.cli", "--port", str(port), *args, name=name, prefix=prefix)
    url = f"{scheme}://127.0.0.1:{port}/"

    def serves() -> bool:
        assert gui.poll() is None, gui.output()
        try:
            with urllib.request.urlopen(url, timeout=1.0, context=context) as response:
                return bool(response.status == 200)
        except OSError:
            return False

    wait_until(serves, START, f"{name} to serve its page")
    return url


@dataclass
class Robot:
    """The secure stack, and the pages' servers on it."""

    stack: Stack
    operator_url: str
    monitor_url: str
    session: zenoh.Session
    """The test's own Zenoh session as operator, to check what the page did."""
