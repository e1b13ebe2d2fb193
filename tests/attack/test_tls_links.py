"""The attack suite (marker ``attack``), Zenoh's links: a router that listens on a ``tls/``
link only refuses a session in clear, and one that trusts another CA; with mutual TLS it also
refuses a client without a certificate of its CA, a CAN bus among them (no frame can be
written onto the robot's bus by a stranger). Each refusal checked beside the session that
is let in, so that the refusal is the check's and not a broken router's."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import can
import pytest
import zenoh
from site_stack import start_router
from support import Processes, make_certificates, open_client

pytestmark = pytest.mark.attack


def opens(session: Callable[[], zenoh.Session]) -> bool:
    try:
        opened = session()
    except zenoh.ZError:
        return False
    opened.close()  # type: ignore[no-untyped-call]
    return True


def test_a_tls_only_router_refuses_a_session_in_clear_or_trusting_another_ca(
    processes: Processes, tmp_path: Path
) -> None:
    ours, theirs = make_certificates(tmp_path / "ours"), make_certificates(tmp_path / "theirs")
    server = ("--tls-cert", str(ours / "server.pem"), "--tls-key", str(ours / "server-key.pem"))
    port = start_router(processes, *server, name="tls-router", ca=ours / "ca.pem")
    assert opens(lambda: open_client(port, ca=ours / "ca.pem"))
    assert not opens(lambda: open_client(port))  # in clear
    assert not opens(lambda: open_client(port, ca=theirs / "ca.pem"))  # a router it cannot trust


def test_a_mutual_tls_router_refuses_a_client_without_a_certificate_of_its_ca(
    processes: Processes, tmp_path: Path
) -> None:
    ours, theirs = make_certificates(tmp_path / "ours"), make_certificates(tmp_path / "theirs")
    port = start_router(
        processes,
        *("--tls-cert", str(ours / "server.pem"), "--tls-key", str(ours / "server-key.pem")),
        *("--tls-client-ca", str(ours / "ca.pem")),
        name="mtls-router",
        ca=ours / "ca.pem",
        client=ours,
    )
    ca = ours / "ca.pem"
    ours_shown = {"certificate": ours / "client.pem", "key": ours / "client-key.pem"}
    theirs_shown = {"certificate": theirs / "client.pem", "key": theirs / "client-key.pem"}
    assert opens(lambda: open_client(port, ca=ca, **ours_shown))
    assert not opens(lambda: open_client(port, ca=ca))  # no certificate
    assert not opens(lambda: open_client(port, ca=ca, **theirs_shown))  # another CA's
    # a server's certificate is not a client's (its key usage says so)
    server_shown = {"certificate": ours / "server.pem", "key": ours / "server-key.pem"}
    assert not opens(lambda: open_client(port, ca=ca, **server_shown))

    # the CAN bus: only a bus that shows the set's client certificate joins, to write frames
    options = {"channel": "robot", "port": port, "tls_ca": str(ca), "open_timeout": 1.0}
    with pytest.raises(can.CanInitializationError):
        can.Bus(interface="zenoh", **options)
    mutual = {"tls_cert": str(ours / "client.pem"), "tls_key": str(ours / "client-key.pem")}
    can.Bus(interface="zenoh", **options, **mutual).shutdown()
