"""The CAN-over-Zenoh bus (``protocol.zenoh_can.bus``) and its router, with real Zenoh
sessions on 127.0.0.1. Every test has a router of its own on a free port, in this process
(``Router``) or, where another process must see it, as ``scara-router``."""

from __future__ import annotations

import importlib.metadata
import json
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator

import can
import pytest
import zenoh
from support import (
    ROOT,
    SLOWDOWN,
    frames_with_every_flag,
    free_port,
    listening_sockets,
    same_frame,
    wait_until,
)

from protocol.zenoh_can import ZenohBus
from protocol.zenoh_can.config import build_zenoh_config, client_config
from protocol.zenoh_can.frame import HEADER, encode_frame
from protocol.zenoh_can.router import Router

PEER = ROOT / "tests" / "peer.py"
COUNT = 5000

pytestmark = pytest.mark.timeout(90)


@pytest.fixture
def local_router() -> Iterator[Router]:
    """A router in this process, on a free port."""
    router = Router(port=free_port())
    yield router
    router.close()


@pytest.fixture
def buses(local_router: Router) -> Iterator[Callable[..., ZenohBus]]:
    """Open buses on the local router through this; all are shut down at the end."""
    opened: list[ZenohBus] = []

    def open_bus(channel: str, **kwargs: object) -> ZenohBus:
        bus = ZenohBus(channel, port=local_router.port, **kwargs)  # type: ignore[arg-type]
        opened.append(bus)
        return bus

    yield open_bus
    for bus in reversed(opened):
        bus.shutdown()


def recv_all(bus: can.BusABC, count: int, timeout: float) -> list[can.Message]:
    """Up to ``count`` frames, or fewer if ``timeout`` s (times SLOWDOWN) pass first."""
    deadline = time.monotonic() + timeout * SLOWDOWN
    got: list[can.Message] = []
    while len(got) < count:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        msg = bus.recv(min(left, 0.5))
        if msg is not None:
            got.append(msg)
    return got


def sequences(frames: list[can.Message]) -> list[int]:
    return [int.from_bytes(m.data[:4], "little") for m in frames if m.arbitration_id == 0x100]


def peer(*args: str) -> subprocess.Popen[str]:
    """``tests/peer.py`` as a separate OS process."""
    return subprocess.Popen(
        [sys.executable, str(PEER), *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish(proc: subprocess.Popen[str], timeout: float) -> str:
    """The output of a peer process that must exit 0 within ``timeout`` s (times SLOWDOWN)."""
    timeout *= SLOWDOWN
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate(timeout=10 * SLOWDOWN)
        raise AssertionError(f"peer process did not finish in {timeout} s: {err}") from None
    assert proc.returncode == 0, err
    return out


# --------------------------------------------------------------------------- opening


def test_a_bus_is_a_client_of_its_router_and_listens_on_no_socket(
    buses: Callable[..., ZenohBus], local_router: Router
) -> None:
    bus = buses("cfg")
    assert bus.zenoh_settings["mode"] == "client"
    assert bus.zenoh_settings["connect/endpoints"] == [f"tcp/127.0.0.1:{local_router.port}"]
    assert bus.router_connected
    # The kernel agrees: the only TCP socket this process listens on is the router's, on
    # 127.0.0.1 (the bus itself listens on nothing).
    listening = listening_sockets()
    if listening is None:
        pytest.skip("no /proc here to read this process's sockets from")
    assert listening == [("127.0.0.1", local_router.port)], listening


def test_no_router_is_reported_with_how_to_start_one(port: int) -> None:
    started = time.monotonic()
    with pytest.raises(can.CanInitializationError) as caught:
        ZenohBus("x", port=port, open_timeout=0.5)
    assert f"127.0.0.1:{port}" in str(caught.value) and "scara-router" in str(caught.value)
    assert time.monotonic() - started < 5.0 * SLOWDOWN


def test_a_port_held_by_a_foreign_program_is_reported(port: int) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as squatter:
        squatter.bind(("127.0.0.1", port))
        squatter.listen(16)
        started = time.monotonic()
        with pytest.raises(can.CanInitializationError) as caught:
            ZenohBus("x", port=port, open_timeout=1.0)
        elapsed = time.monotonic() - started
    assert str(port) in str(caught.value)
    assert elapsed < 10.0 * SLOWDOWN


def test_a_second_router_on_a_taken_port_says_so(local_router: Router) -> None:
    with pytest.raises(can.CanInitializationError, match="already running"):
        Router(port=local_router.port)


def test_a_bus_started_before_its_router_waits_for_it(port: int) -> None:
    opened: list[ZenohBus] = []
    opener = threading.Thread(
        target=lambda: opened.append(ZenohBus("early", port=port, open_timeout=5.0 * SLOWDOWN))
    )
    opener.start()
    time.sleep(0.5)
    router = Router(port=port)
    try:
        opener.join(10 * SLOWDOWN)
        assert opened and opened[0].router_connected
    finally:
        for bus in opened:
            bus.shutdown()
        router.close()


def test_ipv6_loopback_works_too() -> None:
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_STREAM) as probe:
            probe.bind(("::1", 0))
            port6 = int(probe.getsockname()[1])
    except OSError as exc:
        pytest.skip(f"no IPv6 loopback here: {exc}")
    router = Router(host="::1", port=port6)
    a = ZenohBus("v6", host="::1", port=port6)
    b = ZenohBus("v6", host="::1", port=port6)
    try:
        assert b.zenoh_settings["connect/endpoints"] == [f"tcp/[::1]:{port6}"]
        wait_until(lambda: a.has_receivers, 5, "a receiver")
        a.send(can.Message(arbitration_id=5, is_extended_id=False))
        msg = b.recv(5 * SLOWDOWN)
        assert msg is not None and msg.arbitration_id == 5
    finally:
        a.shutdown()
        b.shutdown()
        router.close()


# --------------------------------------------------------------------------- one process


def test_two_buses_exchange_frames_both_ways_with_every_field(
    buses: Callable[..., ZenohBus],
) -> None:
    a = buses("pair")
    b = buses("pair")
    wait_until(lambda: a.has_receivers and b.has_receivers, 5, "the two buses to match")
    sent = frames_with_every_flag()
    for msg in sent:
        a.send(msg)
    got = recv_all(b, len(sent), 5)
    assert len(got) == len(sent)
    for out, back in zip(sent, got, strict=True):
        assert same_frame(back, out, timestamps=False), (out, back)
        assert back.channel == "pair" and back.is_rx
    for msg in reversed(sent):
        b.send(msg)
    got_back = recv_all(a, len(sent), 5)
    expected = list(reversed(sent))
    assert all(same_frame(x, y, timestamps=False) for x, y in zip(got_back, expected, strict=True))
    # No echo of own frames:
    assert a.recv(0.2) is None and b.recv(0.2) is None


def test_frames_sent_together_arrive_together_and_in_order(
    buses: Callable[..., ZenohBus],
) -> None:
    a = buses("together")
    b = buses("together")
    wait_until(lambda: a.has_receivers, 5, "a receiver")
    sent = frames_with_every_flag()
    a.send_many(sent)
    got = recv_all(b, len(sent), 5)
    assert all(same_frame(x, y, timestamps=False) for x, y in zip(got, sent, strict=True))
    assert len({m.timestamp for m in got}) == 1  # received as one


def test_a_received_frame_carries_the_receive_time(buses: Callable[..., ZenohBus]) -> None:
    a = buses("stamp")
    b = buses("stamp")
    wait_until(lambda: a.has_receivers, 5, "a receiver")
    before = time.time()
    a.send(can.Message(timestamp=1.0, arbitration_id=1, is_extended_id=False))
    msg = b.recv(5 * SLOWDOWN)
    assert msg is not None and before <= msg.timestamp <= time.time()


def test_a_signal_handled_while_recv_waits_does_not_make_the_wait_endless(
    buses: Callable[..., ZenohBus],
) -> None:
    """A node's SIGINT handler runs inside the receive it interrupts. With the receive queue a
    queue.SimpleQueue, a handler that outlasted the timeout left get() waiting with a negative
    timeout, which is for ever: a plant stopped after its controller had finished never saw
    its stop. The rescue frame, sent 3 s on (times SLOWDOWN), only keeps a failing test from
    hanging."""
    bus = buses("signalled")
    rescuer = buses("signalled")
    wait_until(lambda: rescuer.has_receivers, 5, "a receiver")
    handled: list[int] = []

    def on_signal(signum: int, frame: object) -> None:
        handled.append(signum)
        time.sleep(0.1)  # longer than the receive's timeout

    previous = signal.signal(signal.SIGUSR2, on_signal)
    poke = threading.Timer(0.02, signal.pthread_kill, (threading.get_ident(), signal.SIGUSR2))
    rescue = threading.Timer(3.0 * SLOWDOWN, rescuer.send, (can.Message(arbitration_id=7),))
    try:
        poke.start()
        rescue.start()
        started = time.monotonic()
        message = bus.recv(timeout=0.05)
        waited = time.monotonic() - started
    finally:
        poke.cancel()
        rescue.cancel()
        signal.signal(signal.SIGUSR2, previous)
    assert handled == [signal.SIGUSR2]
    assert message is None and waited < 1.0 * SLOWDOWN, (message, waited)


def test_receive_own_messages_delivers_own_frames_marked_tx(
    buses: Callable[..., ZenohBus],
) -> None:
    talker = buses("own", receive_own_messages=True)
    other = buses("own")
    wait_until(lambda: talker.has_receivers, 5, "a receiver")
    sent = frames_with_every_flag()[:3]
    for msg in sent:
        talker.send(msg)
    own = recv_all(talker, 3, 5)
    theirs = recv_all(other, 3, 5)
    assert all(same_frame(x, y) for x, y in zip(own, sent, strict=True))
    assert all(same_frame(x, y, timestamps=False) for x, y in zip(theirs, sent, strict=True))
    assert [m.is_rx for m in own] == [False] * 3
    assert [m.is_rx for m in theirs] == [True] * 3
    other.send(sent[0])  # without the option, a bus sees none of its own
    assert other.recv(0.2) is None
    assert talker.recv(5 * SLOWDOWN) is not None


def test_a_malformed_payload_on_the_key_is_counted_and_dropped(
    buses: Callable[..., ZenohBus], local_router: Router
) -> None:
    bus = buses("bad")
    raw = zenoh.open(build_zenoh_config(client_config("127.0.0.1", local_router.port)))
    try:
        publisher = raw.declare_publisher(bus.key)
        wait_until(lambda: bool(publisher.matching_status.matching), 5, "the bus's subscriber")
        good = encode_frame(can.Message(timestamp=1.0, arbitration_id=7, is_extended_id=False))
        malformed = (b"", b"junk", HEADER.pack(1.0, 1, 0x80, 0, 0), HEADER.pack(1.0, 1, 0, 9, 0))
        for payload in malformed:
            publisher.put(payload)
        publisher.put(good)
        msg = bus.recv(5 * SLOWDOWN)
        assert msg is not None and msg.arbitration_id == 7
        assert bus.rx_malformed == 4
        assert bus.recv(0.2) is None
    finally:
        raw.close()


def test_shutdown_is_idempotent_and_closes_the_bus_for_use(
    buses: Callable[..., ZenohBus],
) -> None:
    bus = buses("close")
    blocked: list[BaseException] = []

    def blocked_reader() -> None:
        try:
            bus.recv(None)
        except BaseException as exc:  # recorded for the assertion below
            blocked.append(exc)

    reader = threading.Thread(target=blocked_reader, daemon=True)
    reader.start()
    time.sleep(0.1)
    bus.shutdown()
    bus.shutdown()
    reader.join(5 * SLOWDOWN)
    assert not reader.is_alive(), "recv(None) stayed blocked after shutdown"
    assert blocked and isinstance(blocked[0], can.CanOperationError)
    with pytest.raises(can.CanOperationError, match="shut down"):
        bus.send(can.Message(arbitration_id=1))
    with pytest.raises(can.CanOperationError):
        bus.recv(0)
    assert bus.state is can.BusState.ERROR
    assert not bus.has_receivers and not bus.router_connected


def test_state_channel_info_and_detected_configs(
    buses: Callable[..., ZenohBus], local_router: Router
) -> None:
    bus = buses("info")
    assert bus.state is can.BusState.ACTIVE
    assert "info" in bus.channel_info and str(local_router.port) in bus.channel_info
    assert str(bus) == bus.channel_info
    assert ZenohBus._detect_available_configs() == [{"interface": "zenoh", "channel": "scara"}]
    bus.state = can.BusState.PASSIVE
    with pytest.raises(can.CanOperationError, match="passive"):
        bus.send(can.Message(arbitration_id=1))
    bus.state = can.BusState.ACTIVE
    with pytest.raises(ValueError, match="cannot be sent"):  # never put what peers would drop
        bus.send(can.Message(arbitration_id=0x800, is_extended_id=False))
    with pytest.raises(ValueError, match="ERROR"):
        bus.state = can.BusState.ERROR


def test_buses_go_on_after_the_router_restarts(port: int) -> None:
    router = Router(port=port)
    a = ZenohBus("restart", port=port, linger=0)
    b = ZenohBus("restart", port=port, linger=0)
    try:
        router.close()
        wait_until(lambda: not a.router_connected, 5, "the buses to lose the router")
        router = Router(port=port)
        got: can.Message | None = None
        deadline = time.monotonic() + 15 * SLOWDOWN
        while got is None and time.monotonic() < deadline:  # they reconnect by themselves
            a.send(can.Message(arbitration_id=0x43, is_extended_id=False))
            got = b.recv(0.05)
        assert got is not None and got.arbitration_id == 0x43
    finally:
        a.shutdown()
        b.shutdown()
        router.close()


def test_flush_counts_the_buses_that_confirmed(buses: Callable[..., ZenohBus]) -> None:
    a = buses("flush")
    buses("flush")
    leaving = buses("flush")
    buses("flush/sub")  # another channel: never counted
    patience = 2.0 * SLOWDOWN  # the flush's own bound
    wait_until(lambda: a.flush(patience) == 2, 5, "both other buses to answer the flush query")
    leaving.shutdown()
    started = time.monotonic()
    assert a.flush(patience) == 1
    assert time.monotonic() - started < patience / 2  # not waiting for the bus that left
    lone = buses("alone")
    started = time.monotonic()
    assert lone.flush(patience) == 0
    assert time.monotonic() - started < patience / 2  # nobody to wait for


# --------------------------------------------------------------------------- two processes


def test_receiver_first_then_a_sender_process_that_sends_at_once(
    buses: Callable[..., ZenohBus], local_router: Router
) -> None:
    """Frames sent once ``has_receivers`` holds all arrive, in order."""
    receiver = buses("seq")
    sender = peer(
        "send", "--port", str(local_router.port), "--channel", "seq", "--count", str(COUNT),
        "--wait-receivers", str(20 * SLOWDOWN),
    )  # fmt: skip
    got = recv_all(receiver, COUNT, 30)
    finish(sender, 30)
    assert sequences(got) == list(range(COUNT))


def test_sender_process_first_waits_for_the_receiver_to_appear(
    buses: Callable[..., ZenohBus], local_router: Router
) -> None:
    """No handshake frame is needed: ``has_receivers`` turns true when this receiver's
    subscription has reached the sender, and from then on nothing it sends is lost."""
    sender = peer(
        "send", "--port", str(local_router.port), "--channel", "seq", "--count", str(COUNT),
        "--wait-receivers", str(30 * SLOWDOWN),
    )  # fmt: skip
    assert sender.stdout is not None
    assert json.loads(sender.stdout.readline()) == {"ready": True}
    receiver = buses("seq")
    got = recv_all(receiver, COUNT, 30)
    finish(sender, 30)
    assert sequences(got) == list(range(COUNT))


class SlowBus(ZenohBus):
    """A receiver whose Zenoh thread needs 50 us more per frame (a busy process)."""

    def _on_sample(self, sample: zenoh.Sample) -> None:
        time.sleep(50e-6)
        super()._on_sample(sample)


def test_a_sender_that_shuts_down_at_once_still_reaches_a_slow_receiver(
    local_router: Router,
) -> None:
    """The flush barrier in shutdown(): closing a session drops what is still in flight."""
    count = 30_000
    receiver = SlowBus("slow", port=local_router.port)
    try:
        sender = peer(
            "send", "--port", str(local_router.port), "--channel", "slow", "--count", str(count),
            "--wait-receivers", str(20 * SLOWDOWN), "--linger", str(30 * SLOWDOWN),
        )  # fmt: skip
        got = recv_all(receiver, count, 60)
        finish(sender, 60)
    finally:
        receiver.shutdown()
    assert sequences(got) == list(range(count)), f"{len(got)} of {count} frames"


# --------------------------------------------------------------------------- python-can API


def test_can_bus_finds_the_interface_by_name_and_from_the_environment(
    local_router: Router, monkeypatch: pytest.MonkeyPatch
) -> None:
    registered = importlib.metadata.entry_points(group="can.interface")
    assert any(ep.name == "zenoh" and ep.value.startswith("protocol.") for ep in registered)
    port = local_router.port
    with can.Bus(interface="zenoh", channel="named", port=port) as bus:
        assert isinstance(bus, ZenohBus) and bus.port == port and bus.channel_name == "named"
    monkeypatch.setenv("CAN_INTERFACE", "zenoh")
    monkeypatch.setenv("CAN_CHANNEL", "fromenv")
    monkeypatch.setenv("CAN_CONFIG", json.dumps({"port": port}))
    with can.Bus() as bus:
        assert isinstance(bus, ZenohBus) and bus.port == port and bus.channel_name == "fromenv"
