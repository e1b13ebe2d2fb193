"""Zenoh session settings (``protocol.zenoh_can.config``): buses are clients of one router,
multicast scouting is off, every endpoint is explicit and loopback unless asked otherwise."""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest

from protocol.zenoh_can.config import (
    Tls,
    build_zenoh_config,
    check_host,
    check_port,
    client_config,
    is_loopback,
    key_for_channel,
    router_config,
    served_hosts,
)

FORBIDDEN = ("0.0.0.0", "[::]", "224.0.0.224")


def test_a_bus_is_a_client_of_the_router_and_listens_on_nothing() -> None:
    settings = client_config("127.0.0.1", 17447)
    assert settings["mode"] == "client"
    assert settings["scouting/multicast/enabled"] is False
    assert settings["listen/endpoints"] == []  # unset would mean every interface
    assert settings["connect/endpoints"] == ["tcp/127.0.0.1:17447"]
    assert not any(word in json.dumps(settings) for word in FORBIDDEN)
    config = build_zenoh_config(settings)  # what Zenoh itself reads back
    assert json.loads(config.get_json("mode")) == "client"
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("listen/endpoints")) == []
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/127.0.0.1:17447"]


def test_the_router_listens_on_one_explicit_endpoint() -> None:
    settings = router_config("127.0.0.1", 17447)
    assert settings["mode"] == "router"
    assert settings["scouting/multicast/enabled"] is False
    assert settings["scouting/gossip/enabled"] is False
    assert settings["listen/endpoints"] == ["tcp/127.0.0.1:17447"]
    assert settings["connect/endpoints"] == []
    assert not any(word in json.dumps(settings) for word in FORBIDDEN)
    assert router_config("::1", 9)["listen/endpoints"] == ["tcp/[::1]:9"]


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "224.0.0.224"])
def test_configs_themselves_refuse_wildcards_and_groups(host: str) -> None:
    for build in (client_config, router_config):
        with pytest.raises(can.CanInitializationError):
            build(host, 17447)


@pytest.mark.parametrize("host", ["192.168.1.10", "10.0.0.1", "example.com", "fe80::1"])
def test_a_remote_host_needs_allow_remote(host: str) -> None:
    with pytest.raises(can.CanInitializationError) as caught:
        check_host(host, allow_remote=False)
    assert repr(host) in str(caught.value) and "allow_remote" in str(caught.value)
    assert check_host(host, allow_remote=True) == host


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "[::]", "224.0.0.224", "", "  "])
def test_wildcard_and_multicast_hosts_are_refused_even_with_allow_remote(host: str) -> None:
    with pytest.raises(can.CanInitializationError) as caught:
        check_host(host, allow_remote=True)
    assert repr(host) in str(caught.value)


@pytest.mark.parametrize(
    ("given_host", "normalised"),
    [
        ("127.0.0.1", "127.0.0.1"),
        ("127.1.2.3", "127.1.2.3"),
        ("localhost", "127.0.0.1"),
        ("::1", "::1"),
        ("[::1]", "::1"),
    ],
)
def test_loopback_hosts_are_accepted(given_host: str, normalised: str) -> None:
    assert check_host(given_host, allow_remote=False) == normalised


@pytest.mark.parametrize("port", [0, 65536, -1, True, "17447", 1.5])
def test_ports_outside_1_to_65535_are_refused(port: object) -> None:
    with pytest.raises(can.CanInitializationError, match="port"):
        check_port(port)


@pytest.mark.parametrize("channel", ["", "a*b", "a$b", "a#b", "what?", "two words", "tab\tx"])
def test_bad_channel_names_are_refused_naming_the_value(channel: str) -> None:
    with pytest.raises(can.CanInitializationError) as caught:
        key_for_channel(channel)
    assert repr(channel) in str(caught.value)


@pytest.mark.parametrize("channel", ["ends/", "a//b", "/starts"])
def test_channel_names_that_make_no_key_are_refused(channel: str) -> None:
    with pytest.raises(can.CanInitializationError, match="valid key"):
        key_for_channel(channel)


def test_channel_keys() -> None:
    assert key_for_channel("scara") == "scara/can/scara"
    assert key_for_channel(1) == "scara/can/1"  # python-can casts CAN_CHANNEL=1 to an int


def test_tls_links_are_tls_only_with_the_files_zenoh_reads(tmp_path: Path) -> None:
    for name in ("ca.pem", "server.pem", "server-key.pem", "client.pem", "client-key.pem"):
        (tmp_path / name).write_text("PEM")
    client = Tls.of(tmp_path / "ca.pem", None, None, "client")
    assert client is not None and not client.mutual
    settings = client_config("127.0.0.1", 17448, "operator", "pw", client)
    assert settings["connect/endpoints"] == ["tls/127.0.0.1:17448"]
    assert settings["transport/link/tls/root_ca_certificate"] == str(tmp_path / "ca.pem")
    assert "transport/link/tls/enable_mtls" not in settings
    mutual = Tls.of(tmp_path / "ca.pem", tmp_path / "client.pem", tmp_path / "client-key.pem",
                    "client")  # fmt: skip
    assert mutual is not None and mutual.mutual
    settings = client_config("::1", 9, tls=mutual)
    assert settings["connect/endpoints"] == ["tls/[::1]:9"]
    assert settings["transport/link/tls/enable_mtls"] is True
    assert settings["transport/link/tls/connect_certificate"] == str(tmp_path / "client.pem")
    router = Tls.of(None, tmp_path / "server.pem", tmp_path / "server-key.pem", "router")
    settings = router_config("127.0.0.1", 17448, tls=router)
    assert settings["listen/endpoints"] == ["tls/127.0.0.1:17448"]  # and nothing in clear
    assert settings["transport/link/tls/listen_private_key"] == str(tmp_path / "server-key.pem")
    assert "transport/link/tls/enable_mtls" not in settings
    asks = Tls.of(tmp_path / "ca.pem", tmp_path / "server.pem", tmp_path / "server-key.pem",
                  "router")  # fmt: skip
    assert router_config("127.0.0.1", 1, tls=asks)["transport/link/tls/enable_mtls"] is True
    assert Tls.of(None, None, None, "client") is None


@pytest.mark.parametrize(
    ("files", "side", "refused"),
    [
        ((None, "server.pem", None), "router", "give both"),
        ((None, None, "server-key.pem"), "router", "give both"),
        (("ca.pem", None, None), "router", "needs its certificate"),
        ((None, "client.pem", "client-key.pem"), "client", "needs the CA"),
        (("missing.pem", None, None), "client", "no such file"),
    ],
)
def test_tls_files_that_cannot_make_a_link_are_refused_naming_what_is_missing(
    tmp_path: Path, files: tuple[str | None, ...], side: str, refused: str
) -> None:
    for name in ("ca.pem", "server.pem", "server-key.pem", "client.pem", "client-key.pem"):
        (tmp_path / name).write_text("PEM")
    paths = [None if name is None else tmp_path / name for name in files]
    with pytest.raises(can.CanInitializationError, match=refused):
        Tls.of(*paths, side)


def test_served_hosts_are_loopbacks_the_listening_address_and_the_names_given() -> None:
    assert served_hosts("127.0.0.1") == ["localhost", "127.0.0.1", "::1"]
    assert served_hosts("[FE80::1]", ["Robot.LAN"]) == [
        "localhost", "127.0.0.1", "::1", "fe80::1", "robot.lan",
    ]  # fmt: skip
    assert is_loopback("[::1]") and is_loopback("LOCALHOST") and not is_loopback("10.0.0.1")
