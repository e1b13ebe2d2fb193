"""Opening a node's bus (``protocol.bus``): python-can's own configuration decides."""

from __future__ import annotations

import argparse

import pytest

from protocol.bus import parse_options, resolve_transport


def test_transport_comes_from_flags_then_python_can_config_then_default(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    assert resolve_transport("virtual", "x") == ("virtual", "x")
    monkeypatch.setenv("CAN_INTERFACE", "udp_multicast")
    monkeypatch.setenv("CAN_CHANNEL", "239.74.163.2")
    assert resolve_transport(None, None) == ("udp_multicast", "239.74.163.2")
    monkeypatch.delenv("CAN_INTERFACE")
    monkeypatch.delenv("CAN_CHANNEL")
    monkeypatch.setenv("HOME", "/nonexistent")
    interface, _ = resolve_transport(None, None)
    assert interface in ("socketcan", "zenoh")
    assert parse_options(["port=17447", "express=false", "host=127.0.0.1"]) == {
        "port": 17447,
        "express": False,
        "host": "127.0.0.1",
    }


def test_bus_options_that_are_not_key_value_are_refused() -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="key=value"):
        parse_options(["port"])
