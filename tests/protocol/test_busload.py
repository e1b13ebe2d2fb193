"""Bus load (the ``protocol.busload`` package): the worst-case frame length, the schedule
taken from the DBC's attributes, the lower bound, and the scara-busload report."""

from __future__ import annotations

from typing import Any

import cantools
import pytest

from protocol.busload.bound import minimum_load, quantity_bits
from protocol.busload.load import bus_load, frame_bits, max_rate_hz
from protocol.busload.report import main
from protocol.codec import DBC_TEXT

DATABASE: Any = cantools.database.load_string(DBC_TEXT, database_format="dbc")
DLC = {m.name: m.length for m in DATABASE.messages}
PER_TICK = ("JointVelocityCommand", "JointState1", "JointState2", "JointState3")
CYCLIC = {  # name: frames per second, from the DBC's attributes
    m.name: 1000.0 / m.cycle_time
    for m in DATABASE.messages
    if m.dbc.attributes.get("ScaraSchedule")
    and m.dbc.attributes["ScaraSchedule"].definition.choices[
        m.dbc.attributes["ScaraSchedule"].value
    ]
    == "cyclic"
}


def test_frame_bits_by_hand() -> None:
    # DLC 8: SOF 1 + ID 11 + RTR, IDE, r0 3 + DLC 4 + data 64 + CRC 15 = 98 bits stuffed,
    # worst case one stuff bit per 4 after the first: (98 - 1) // 4 = 24; plus CRC
    # delimiter 1, ACK 2, EOF 7, IFS 3 = 13 never stuffed: 98 + 24 + 13 = 135.
    assert frame_bits(8) == 135
    # DLC 0: 34 stuffed bits, (34 - 1) // 4 = 8 stuff bits, 13 more: 55.
    assert frame_bits(0) == 55
    assert frame_bits(8, stuffing=False) == 111
    assert frame_bits(0, stuffing=False) == 47
    for dlc in range(9):  # Davis et al.'s closed form for 11-bit IDs
        assert frame_bits(dlc) == 55 + 10 * dlc
        assert frame_bits(dlc) == 8 * dlc + 47 + (34 + 8 * dlc - 1) // 4
    for bad in (-1, 9):
        with pytest.raises(ValueError):
            frame_bits(bad)


def test_every_dbc_message_is_counted_with_its_dlc() -> None:
    load = bus_load(500.0)
    assert {f.name: f.dlc for f in load.frames} == DLC
    assert all(f.bits == frame_bits(f.dlc) for f in load.frames)


def test_schedule_is_the_dbcs_cycle_time_attributes() -> None:
    rate = 500.0
    per_second = {f.name: f.frames_per_s for f in bus_load(rate).frames}
    for message in DATABASE.messages:
        schedule = message.dbc.attributes.get("ScaraSchedule")
        kind = schedule.definition.choices[schedule.value] if schedule else "event"
        if kind == "tick":
            assert message.cycle_time == 1000 / rate  # the default rate's period, in ms
            assert per_second[message.name] == rate
        elif kind == "cyclic":
            assert per_second[message.name] == 1000 / message.cycle_time
        else:  # events, and the lockstep-only StepSync in real time
            assert per_second[message.name] == 0.0
    assert set(PER_TICK) <= {name for name, hz in per_second.items() if hz == rate}
    assert per_second["ControllerStatus"] == per_second["PlantStatus"] == 10.0


def test_load_scales_linearly_with_rate() -> None:
    per_tick = sum(frame_bits(DLC[name]) for name in PER_TICK)
    status = sum(hz * frame_bits(DLC[name]) for name, hz in CYCLIC.items())
    for rate in (100.0, 250.0, 500.0, 1000.0, 2000.0):
        load = bus_load(rate)
        assert load.bits_per_s == pytest.approx(per_tick * rate + status)
        assert load.fraction == pytest.approx(load.bits_per_s / 1_000_000)
    one, two, three = (bus_load(r).fraction for r in (400.0, 800.0, 1200.0))
    assert two - one == pytest.approx(three - two)
    assert bus_load(500.0, bitrate=500_000).fraction == pytest.approx(2 * bus_load(500.0).fraction)


def test_lockstep_adds_the_step_sync_frame() -> None:
    for rate in (500.0, 1000.0):
        real_time, lockstep = bus_load(rate), bus_load(rate, lockstep=True)
        step = {f.name: f for f in lockstep.frames}["StepSync"]
        assert step.frames_per_s == rate
        assert lockstep.frames_per_s - real_time.frames_per_s == pytest.approx(rate)
        assert lockstep.bits_per_s - real_time.bits_per_s == pytest.approx(frame_bits(6) * rate)


def test_real_time_load_at_500_hz_is_under_30_percent() -> None:
    assert bus_load(500.0).fraction < 0.30
    # The known shortfall: four frames every tick, about 51 % at 1 kHz.
    # Four frames (8, 7, 7, 7 bytes) a tick at 55 + 10 s bits each, four of 8 bytes at 10 Hz:
    per_second = 1000 * (4 * 55 + 10 * (8 + 7 + 7 + 7)) + 10 * 4 * frame_bits(8)
    assert bus_load(1000.0).fraction == pytest.approx(per_second / 1_000_000)
    rate = max_rate_hz(0.30)
    assert bus_load(rate).fraction == pytest.approx(0.30)


def test_bad_arguments_are_refused() -> None:
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            bus_load(bad)
    with pytest.raises(ValueError):
        bus_load(500.0, bitrate=0)


def test_minimum_load_by_hand() -> None:
    # 1 urad over 300 deg = 5.236 rad: 5 235 988 codes, 23 bits; 290 deg: 23 bits;
    # 1 um over 0.2 m: 200 001 codes, 18 bits; 1e-3 rad/s over +-7.85: 15 701 codes, 14 bits;
    # over +-12.5: 25 001, 15 bits; 1e-4 m/s over +-1.0: 20 001, 15 bits.
    assert quantity_bits(-1.0, 1.0, 1e-4) == 15
    assert quantity_bits(0.0, 0.2, 1e-6) == 18
    assert quantity_bits(0.0, 1.0, 1.0) == 1
    assert quantity_bits(0.0, 3.0, 1.0) == 2
    assert quantity_bits(0.0, 4.0, 1.0) == 3
    minimum = minimum_load()
    controller, plant = minimum.senders
    assert [q.bits for q in controller.quantities] == [14, 15, 15]
    assert [q.bits for q in plant.quantities] == [23, 23, 18, 14, 15, 15]
    # controller: 44 + 12 bits = 7 bytes, one frame: 55 + 70 = 125 bits;
    # plant: 108 bits need 3 frames (2 * 52 < 108), 108 + 36 = 144 bits = 18 bytes:
    # 3 * 55 + 180 = 345 bits.
    assert (controller.frames, controller.bits) == (1, 125)
    assert (plant.frames, plant.bits) == (3, 345)
    assert minimum.bits_per_tick == 470
    assert minimum.fraction(1000.0) == pytest.approx(0.470)
    assert minimum.fraction(1000.0, stuffing=False) == pytest.approx(0.388)
    assert minimum.fraction(1000.0, stuffing=False) > 0.30  # 1 kHz cannot reach 30 %
    assert minimum.fraction(500.0) < 0.30
    assert minimum.bits_per_tick <= sum(frame_bits(DLC[name]) for name in PER_TICK)


def test_main_prints_a_table_and_exits_0(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 0
    out = capsys.readouterr().out
    table = [line for line in out.splitlines() if line.startswith("| ")]
    assert table[0].startswith("| Frame | ID | DLC | Bits | Schedule | 500 Hz")
    assert "1000 Hz: bit/s" in table[0]
    assert any(line.startswith("| JointVelocityCommand | 0x100 | 8 | 135 |") for line in table)
    assert "| 26.0 % |" in out and "| 51.5 % |" in out
    assert "Under 30.0 %: 500 Hz; at or above: 1000 Hz." in out
    assert "1000 Hz: at least 47.0 %" in out

    assert main(["--rate", "250", "--bitrate", "500000", "--lockstep"]) == 0
    out = capsys.readouterr().out
    assert "lockstep mode, 500 kbit/s" in out and "250 Hz: frames/s" in out


def test_help_and_bad_options(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    assert "bus load" in capsys.readouterr().out
    with pytest.raises(SystemExit) as info:
        main(["--rate", "-5"])
    assert info.value.code == 2
