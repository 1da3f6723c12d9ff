"""Frames/s received over OpenIGTLink on loopback for 820x616 uint8 frames, and frames lost.

Target: at least 30 frames/s without loss. ``IgtlStreamer`` (core/acquisition/igtl.py) sends IMAGE +
TRANSFORM ProbeToReference per frame, as fast as possible and at 30 frames/s. Two receivers:

- ``IgtlSource`` (core/acquisition/imagesource.py): our receive loop on pyigtl's message classes, read with
  ``frames()``, which yields every frame;
- pyigtl's stock ``OpenIGTLinkClient`` read with ``wait_for_message``, for comparison: it keeps
  only the newest message per device (``incoming_messages`` is a dict) and ``wait_for_message``
  polls every 10 ms, so it loses every frame that arrives between two reads. Its receive loop
  also drops a partly received header on its 10 ms socket time-out (the stream then
  desynchronises) and never notices a closed connection (``recv`` returning b"" is taken as "no
  message yet"), which is why IgtlSource reads the socket itself and only uses pyigtl's message
  classes to unpack.

Each frame carries its sequence number in its first four pixels, so losses are counted exactly.

Run: .venv/bin/python benchmarks/bench_igtl.py
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pyigtl

from probecal.core.acquisition.igtlsource import IgtlSource
from probecal.core.acquisition.igtlstreamer import IgtlStreamer
from probecal.core.acquisition.imagesource import ImageSourceError, SourceFrame

ROWS, COLS = 616, 820
FAST_FRAMES = 600
PACED_FRAMES = 150  # 5 s at 30 frames/s
TIMEOUT_S = 3.0


def frames(n: int) -> Iterator[SourceFrame]:
    """n speckle-like frames with their sequence number in pixels [0, 0:4], stamped when sent."""
    rng = np.random.default_rng(0)
    bases = rng.integers(0, 256, (4, ROWS, COLS), dtype=np.uint8)
    pose = np.eye(4)
    for i in range(n):
        image = bases[i % len(bases)].copy()
        image[0, :4] = np.frombuffer(np.uint32(i).tobytes(), np.uint8)
        pose[:3, 3] = [i * 0.1, 0.0, 200.0]
        now = time.time()
        yield SourceFrame(image, now, i, pose.copy(), now, (0.1, 0.1))


def sequence(image: np.ndarray) -> int:
    return int(np.frombuffer(np.ascontiguousarray(image.reshape(-1)[:4]).tobytes(), np.uint32)[0])


def with_igtl_source(n: int, rate_hz: float | None) -> tuple[list[int], list[float], str]:
    with IgtlStreamer() as streamer:
        source = IgtlSource("127.0.0.1", streamer.port)
        source.open()
        streamer.play(frames(n), rate_hz)
        seen, times, note = [], [], ""
        try:
            for frame in source.frames(TIMEOUT_S):
                seen.append(sequence(frame.image))
                times.append(time.perf_counter())
                if frame.tool_to_base is None:
                    note = "a frame came without its pose"
                if len(seen) == n:
                    break
        except ImageSourceError as exc:
            note = str(exc)
        finally:
            source.close()
    return seen, times, note


def with_stock_pyigtl(n: int, rate_hz: float | None) -> tuple[list[int], list[float], str]:
    with IgtlStreamer() as streamer:
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", streamer.port)
        streamer.play(frames(n), rate_hz)
        seen, times = [], []
        try:
            while (message := client.wait_for_message("Image", timeout=TIMEOUT_S)) is not None:
                seen.append(sequence(message.image))
                times.append(time.perf_counter())
                if seen[-1] == n - 1:
                    break
        finally:
            client.stop()
    return seen, times, ""


def report(label: str, n: int, seen: list[int], times: list[float], note: str) -> None:
    rate = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 0.0
    lost = n - len(set(seen))
    in_order = all(b > a for a, b in zip(seen, seen[1:]))
    mb_s = rate * ROWS * COLS / 1e6
    problems = [text for bad, text in ((lost > 0, "LOSES FRAMES"), (rate < 29.0, "TOO SLOW")) if bad]
    status = ", ".join(problems) or "ok"
    print(
        f"{label:<54} sent {n:4d}  received {len(seen):4d}  lost {lost:4d}  "
        f"{rate:7.1f} frames/s ({mb_s:6.1f} MB/s)  {'in order' if in_order else 'OUT OF ORDER'}  {status}"
    )
    if note:
        print(f"{'':<54} note: {note}")


def main() -> None:
    print(f"OpenIGTLink on loopback, {COLS}x{ROWS} uint8 IMAGE + TRANSFORM per frame")
    receivers = ((with_igtl_source, "IgtlSource.frames()"), (with_stock_pyigtl, "pyigtl OpenIGTLinkClient (stock)"))
    for receiver, name in receivers:
        for n, rate_hz in ((FAST_FRAMES, None), (PACED_FRAMES, 30.0)):
            pace = "as fast as possible" if rate_hz is None else f"at {rate_hz:.0f} frames/s"
            report(f"{name}, {pace}", n, *receiver(n, rate_hz))


if __name__ == "__main__":
    main()
