"""Recording and replay benchmark, side by side in one run.

1. A 1 kHz real-time run of ``reference`` recorded by ``scara-run`` (its recorder on): the
   source of the frames below, and the frame rate a 1 kHz run puts on the bus.
2. **Recorder throughput and file size**: the recorder's writer thread's work (raw frame +
   decoded state + zstd chunks, to a file) on those frames, in this process, as frames per
   second (best of 5), and the size of the file it makes; in turns, chunks ended only at
   ``CHUNK_SIZE`` (the recorder before chunks by time) and also ``FLUSH_PERIOD`` of bus time
   after their first frame, with the recorder's counts and a flush to the OS (as
   ``scara-record`` does now, so that a kill -9 loses at most that).
3. **Replay as fast as possible** onto CAN-over-Zenoh: ``scara-replay --as-fast-as-possible``
   from the MCAP file, and python-can's ``can.player --ignore-timestamps -g 0`` from the same
   frames as ``.blf``,
   received by a listener here (frames per second from the first to the last frame).
4. **Replay at recorded pace** (``--rate 1``): each frame's arrival here against its recorded
   time, both from the first frame; the error's p99.

Run from the project root: ``python benchmarks/bench_record.py [--json PATH]``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from bench_link import router  # noqa: E402

from protocol.scenario import load_scenario  # noqa: E402
from recorder.mcap_can import (  # noqa: E402
    FLUSH_PERIOD,
    FrameChannels,
    RecorderCounts,
    counts_channel,
    end_chunk,
    finish,
    open_writer,
)
from recorder.node import StateChannels  # noqa: E402
from recorder.replay import read_frames  # noqa: E402

TARGET_HEADROOM = 20.0
TARGET_FAST = 150_000.0
TARGET_PACE_MS = 1.0
OURS = "scara-replay (MCAP)"
THEIRS = "can.player --ignore-timestamps -g 0 (BLF)"


def record_run(port: int, out: Path) -> list[can.Message]:
    command = [
        sys.executable, "-m", "sim.launch", "reference", "--clock", "realtime", "--rate", "1000",
        "--out", str(out), "--interface", "zenoh", "--channel", f"rec{port}",
        "--bus-option", f"port={port}",
    ]  # fmt: skip
    subprocess.run(command, cwd=ROOT, check=True, capture_output=True)
    return list(read_frames(out / "run.mcap"))


def recorder_counts() -> dict[str, Any]:
    return {"frames": 0, "bad_frames": 0, "published": {}, "dropped": {}, "rates_hz": {}}


def write_file(frames: list[can.Message], path: Path, by_time: bool) -> float:
    """Write ``frames`` as the recorder's writer thread does; the frames per second.
    ``by_time``: a chunk also ends :data:`FLUSH_PERIOD` of bus time after its first frame."""
    robot = load_scenario("reference").robot
    with path.open("wb") as stream:
        writer = open_writer(stream)
        raw, state = FrameChannels(writer), StateChannels(writer, robot)
        counts = counts_channel(writer)
        due: float | None = None
        started = time.perf_counter()
        for received, message in enumerate(frames, 1):
            raw.write(message)
            state.feed(message, recorder_counts)
            if not by_time:
                continue
            if due is None:
                due = message.timestamp + FLUSH_PERIOD
            elif message.timestamp >= due:
                stamp = round(message.timestamp * 1e9)
                end_chunk(writer, counts, RecorderCounts(received, 0), stamp)
                due = None
        finish(writer)
        return len(frames) / (time.perf_counter() - started)


def recorder_throughput(
    frames: list[can.Message], folder: Path, repeats: int = 5
) -> dict[bool, tuple[float, int]]:
    """By chunking (by time or not): the best frames/s of ``repeats``, taken in turns so that
    the machine's noise falls on both alike, and the file's size in bytes."""
    best = dict.fromkeys((False, True), 0.0)
    for _ in range(repeats):
        for by_time in best:
            path = folder / f"throughput_{by_time}.mcap"
            best[by_time] = max(best[by_time], write_file(frames, path, by_time))
    return {
        by_time: (rate, (folder / f"throughput_{by_time}.mcap").stat().st_size)
        for by_time, rate in best.items()
    }


class Listener:
    """Receives on the bus in a thread; arrival times of the frames."""

    def __init__(self, port: int) -> None:
        self.bus = can.Bus(interface="zenoh", channel=f"rec{port}", port=port)
        self.times: list[float] = []
        self.running = True
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        time.sleep(0.5)

    def _run(self) -> None:
        while self.running:
            message = self.bus.recv(0.1)
            if message is not None:
                self.times.append(message.timestamp)

    def take(self, expected: int, timeout: float = 60.0) -> list[float]:
        deadline = time.monotonic() + timeout
        while len(self.times) < expected and time.monotonic() < deadline:
            time.sleep(0.05)
        taken, self.times = self.times, []
        return taken

    def close(self) -> None:
        self.running = False
        self._thread.join()
        self.bus.shutdown()


def play(command: list[str]) -> None:
    subprocess.run(command, cwd=ROOT, check=True, capture_output=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--json", type=Path, help="also write the numbers as JSON here")
    args = parser.parse_args(argv)
    with router() as port, tempfile.TemporaryDirectory() as folder:
        out = Path(folder)
        print("[1/4] a 1 kHz real-time run, recorded", file=sys.stderr)
        frames = record_run(port, out / "run")
        run_seconds = load_scenario("reference").duration
        bus_rate = len(frames) / run_seconds
        print("[2/4] recorder throughput and file size, chunks by size / by time", file=sys.stderr)
        chunkings = recorder_throughput(frames, out)
        (by_size, size_by_size), (written, size_by_time) = chunkings[False], chunkings[True]
        mcap = out / "run" / "run.mcap"
        blf = out / "run.blf"
        with can.Logger(blf) as writer:
            for message in frames:
                writer.on_message_received(message)
        bus = ["--interface", "zenoh", "--channel", f"rec{port}", "--bus-option", f"port={port}"]
        listener = Listener(port)
        print("[3/4] replay as fast as possible", file=sys.stderr)
        rates: dict[str, list[float]] = {OURS: [], THEIRS: []}
        for _ in range(3):
            play(
                [sys.executable, "-m", "recorder.replay", str(mcap), "--as-fast-as-possible", *bus]
            )
            got = listener.take(len(frames))
            rates[OURS].append(len(got) / (got[-1] - got[0]))
            play([
                sys.executable, "-m", "can.player", "-i", "zenoh", "-c", f"rec{port}",
                "--bus-kwargs", f"port={port}", "--ignore-timestamps", "-g", "0", "--", str(blf),
            ])  # fmt: skip
            got = listener.take(len(frames))
            rates[THEIRS].append(len(got) / (got[-1] - got[0]))
        print("[4/4] replay at the recorded pace (first 5 s)", file=sys.stderr)
        play([sys.executable, "-m", "recorder.replay", str(mcap), "--until", "5", *bus])
        recorded = np.asarray(
            [m.timestamp for m in frames if m.timestamp - frames[0].timestamp <= 5]
        )
        arrived = np.asarray(listener.take(len(recorded)))
        listener.close()
    count = min(len(recorded), len(arrived))
    error = np.abs((arrived[:count] - arrived[0]) - (recorded[:count] - recorded[0])) * 1e3
    pace_p99 = float(np.percentile(error, 99))
    ours = float(np.median(rates[OURS]))
    theirs = float(np.median(rates[THEIRS]))

    def verdict(passed: bool) -> str:
        return "PASS" if passed else "FAIL"

    lines = [
        "| measure | result | target | |",
        "|---|---|---|---|",
        f"| frames on the bus in a 1 kHz run | {bus_rate:,.0f} frames/s ({len(frames):,} in "
        f"{run_seconds:g} s) | | |",
        f"| recorder: frames written (raw + decoded state, zstd), chunks of "
        f"{FLUSH_PERIOD * 1e3:g} ms | {written:,.0f} frames/s "
        f"({written / bus_rate:.0f}x the 1 kHz run) | >= {TARGET_HEADROOM:g}x "
        f"| {verdict(written / bus_rate >= TARGET_HEADROOM)} |",
        f"| recorder: the same, chunks by size only (before) | {by_size:,.0f} frames/s "
        f"(chunks by time: {written / by_size:.2f}x) | | |",
        f"| recorder: file size, chunks of {FLUSH_PERIOD * 1e3:g} ms / by size only | "
        f"{size_by_time / 1e6:.2f} MB / {size_by_size / 1e6:.2f} MB "
        f"({size_by_time / size_by_size:.2f}x) | | |",
        f"| `scara-replay --as-fast-as-possible`, MCAP onto Zenoh (median of 3) "
        f"| {ours:,.0f} frames/s | >= {TARGET_FAST:,.0f} | {verdict(ours >= TARGET_FAST)} |",
        f"| `can.player --ignore-timestamps -g 0`, the same frames from BLF "
        f"| {theirs:,.0f} frames/s | below ours | {verdict(ours > theirs)} |",
        f"| `scara-replay --rate 1`: arrival vs recorded time, p99 ({count:,} frames) "
        f"| {pace_p99:.3f} ms | <= {TARGET_PACE_MS:g} ms | {verdict(pace_p99 <= TARGET_PACE_MS)} |",
    ]
    print("\n".join(lines))
    if args.json:
        numbers = {
            "bus_frames_per_s": bus_rate,
            "recorder_frames_per_s": written,
            "recorder_frames_per_s_chunks_by_size": by_size,
            "file_bytes": size_by_time,
            "file_bytes_chunks_by_size": size_by_size,
            "replay_fast": rates,
            "pace_p99_ms": pace_p99,
        }
        args.json.write_text(json.dumps(numbers, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
