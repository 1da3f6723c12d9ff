"""Live image paths: OpenIGTLink in and out on loopback, video files, session replay, pose pairing."""

from __future__ import annotations

import re
import signal
import socket
import threading
import time

import cv2
import numpy as np
import pyigtl
import pytest
from scipy.spatial.transform import Rotation

from probecal.app.rigspec import parse_image_spec
from probecal.core.acquisition.igtl import IgtlPublisher, image_message
from probecal.core.acquisition.igtlsource import IgtlSource, gray_frame
from probecal.core.acquisition.igtlstreamer import IgtlStreamer
from probecal.core.acquisition.imagesource import (
    BUFFER_FRAMES,
    MAX_RATE_HZ,
    ImageSourceError,
    SourceFrame,
    StreamFormat,
    ThreadedSource,
)
from probecal.core.acquisition.videosource import ReplaySource, VideoSource, replay_times
from probecal.core.errors import InputError
from probecal.core.geometry.transforms import make_transform
from probecal.core.io.manifest import Manifest
from probecal.core.io.session import SessionWriter, load_session
from tests.support.waiting import wait_until

ROWS, COLS = 48, 64
HANG_GUARD_S = 10.0  # generous bound on anything that must not hang; not a speed target


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def pose(i: int) -> np.ndarray:
    rotation = Rotation.from_euler("xyz", [3 * i, -2 * i, 10 + i], degrees=True)
    return make_transform(rotation, [100 + i, -50.5, 300.25])


def make_frames(n: int, with_pose: bool, spacing=(0.3, 0.25)) -> list[SourceFrame]:
    rng = np.random.default_rng(n)
    return [
        SourceFrame(
            rng.integers(0, 256, (ROWS, COLS), dtype=np.uint8),
            1_700_000_000.0 + 0.05 * i,
            i,
            pose(i) if with_pose else None,
            1_700_000_000.0 + 0.05 * i if with_pose else None,
            spacing,
        )
        for i in range(n)
    ]


def endless_frames():
    i = 0
    while True:
        yield SourceFrame(np.full((ROWS, COLS), i % 256, np.uint8), time.time(), i)
        i += 1


def receive(source: IgtlSource, n: int) -> list[SourceFrame]:
    frames = []
    for frame in source.frames(timeout_s=5.0):
        frames.append(frame)
        if len(frames) == n:
            break
    return frames


# --- OpenIGTLink in --------------------------------------------------------------------------


@pytest.mark.parametrize("with_pose", [False, True], ids=["image-only", "image+transform"])
def test_igtl_frames_arrive_exactly(with_pose):
    sent = make_frames(12, with_pose)
    with IgtlStreamer() as streamer, IgtlSource("127.0.0.1", streamer.port) as source:
        streamer.play(sent, rate_hz=200.0)
        got = receive(source, len(sent))
    assert [f.index for f in got] == list(range(len(sent)))
    for s, g in zip(sent, got):
        assert g.image.dtype == np.uint8 and np.array_equal(g.image, s.image)
        assert g.timestamp == pytest.approx(s.timestamp, abs=1e-6)
        assert g.pixel_spacing_mm == (np.float32(0.3), np.float32(0.25))
        if with_pose:
            assert np.array_equal(g.tool_to_base, s.tool_to_base.astype(np.float32))
            assert g.pose_timestamp == pytest.approx(s.pose_timestamp, abs=1e-6)
        else:
            assert g.tool_to_base is None and g.pose_timestamp is None


@pytest.fixture
def pyigtl_server():
    """pyigtl's own server (it hooks SIGINT/SIGTERM; they are restored afterwards)."""
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    server = pyigtl.OpenIGTLinkServer(port=0)
    yield server
    server.stop()
    for s, handler in handlers.items():
        signal.signal(s, handler)


def test_igtl_from_a_pyigtl_server_shapes_colour_and_pose_first(pyigtl_server):
    rng = np.random.default_rng(1)
    plain = rng.integers(0, 256, (ROWS, COLS), dtype=np.uint8)
    rgb = rng.integers(0, 256, (ROWS, COLS, 3), dtype=np.uint8)
    t = 1_700_000_100.5
    with IgtlSource("127.0.0.1", pyigtl_server.server_address[1]) as source:
        deadline = time.monotonic() + HANG_GUARD_S
        while not pyigtl_server.is_connected():
            assert time.monotonic() < deadline, "pyigtl server never saw the connection"
            time.sleep(0.01)
        messages = [
            pyigtl.TransformMessage(pose(1), timestamp=t, device_name="ProbeToReference"),  # pose first
            pyigtl.ImageMessage(plain[np.newaxis], np.diag([0.2, 0.15, 1, 1]), timestamp=t, device_name="Image"),
            pyigtl.ImageMessage(plain, timestamp=t + 1, device_name="Image"),  # 2D: arrives as (rows, cols, 1)
            pyigtl.ImageMessage(rgb[np.newaxis], timestamp=t + 2, device_name="Image"),
            pyigtl.ImageMessage(plain.astype(np.uint16)[np.newaxis], timestamp=t + 3, device_name="Image"),
        ]
        for message in messages:
            pyigtl_server.send_message(message, wait=False)
        got = receive(source, 3)
        with pytest.raises(ImageSourceError, match="bad IMAGE message 'Image'.*only 8-bit"):
            source.latest(timeout_s=5.0)
    assert np.array_equal(got[0].image, plain) and np.array_equal(got[1].image, plain)
    assert np.array_equal(got[2].image, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    assert got[0].pixel_spacing_mm == (np.float32(0.2), np.float32(0.15))
    assert got[1].pixel_spacing_mm is None  # unit spacing: frames in pixels, as PLUS sends them
    assert np.array_equal(got[0].tool_to_base, pose(1).astype(np.float32)) and got[0].pose_timestamp == t
    assert got[1].tool_to_base is None  # the only pose is 1 s away


def test_gray_frame_shapes_and_refusals():
    image = np.arange(12, dtype=np.uint8).reshape(3, 4)
    spacing = np.diag([0.5, 0.4, 2.0, 1.0])
    assert np.array_equal(gray_frame(image[np.newaxis], spacing)[0], image)
    assert gray_frame(image[np.newaxis], spacing)[1] == (0.5, 0.4)
    # A 2D array through pyigtl: (k=rows, j=cols, i=1), so columns run along j and rows along k.
    assert np.array_equal(gray_frame(image[..., np.newaxis], spacing)[0], image)
    assert gray_frame(image[..., np.newaxis], spacing)[1] == (0.4, 2.0)
    assert gray_frame(image[np.newaxis], np.eye(4))[1] is None
    rgba = np.dstack([image, image, image, np.full_like(image, 255)])
    assert np.array_equal(gray_frame(rgba[np.newaxis], np.eye(4))[0], image)
    with pytest.raises(ValueError, match="volume"):
        gray_frame(np.zeros((2, 3, 4), np.uint8), np.eye(4))
    with pytest.raises(ValueError, match="only 8-bit"):
        gray_frame(np.zeros((1, 3, 4), np.float32), np.eye(4))
    with pytest.raises(ValueError, match="2 components"):
        gray_frame(np.zeros((1, 3, 4, 2), np.uint8), np.eye(4))


def test_igtl_stalled_stream_raises_within_the_timeout():
    with IgtlStreamer() as streamer, IgtlSource("127.0.0.1", streamer.port) as source:
        streamer.play(endless_frames(), rate_hz=50.0)
        source.latest(timeout_s=5.0)
        streamer.stall()
        start = time.monotonic()
        stalled = r"igtl:127\.0\.0\.1:\d+: no image for 0\.3 s \(stream stalled\)"
        with pytest.raises(ImageSourceError, match=stalled):
            for _ in range(100):
                source.latest(timeout_s=0.3)
        assert time.monotonic() - start < HANG_GUARD_S
        with pytest.raises(ImageSourceError, match="stalled"):
            list(source.frames(timeout_s=0.3))
        streamer.resume()
        assert source.latest(timeout_s=5.0).image.shape == (ROWS, COLS)


def test_igtl_killed_server_raises_after_every_frame_received():
    sent = make_frames(6, with_pose=True)
    received = []
    with IgtlStreamer() as streamer, IgtlSource("127.0.0.1", streamer.port) as source:
        streamer.play(sent)
        assert streamer.wait_done(HANG_GUARD_S)
        with pytest.raises(ImageSourceError, match="connection closed by the server"):
            for frame in source.frames(timeout_s=5.0):
                received.append(frame)
                if len(received) == len(sent):
                    streamer.kill()
    assert len(received) == len(sent) and all(f.tool_to_base is not None for f in received)


def test_igtl_connection_refused():
    source = IgtlSource("127.0.0.1", free_port())
    with pytest.raises(ImageSourceError, match=r"igtl:127\.0\.0\.1:\d+: connection refused"):
        source.open()
    with pytest.raises(ImageSourceError, match="not open"):
        source.latest(timeout_s=0.1)


@pytest.mark.parametrize("corrupt", ["crc", "size"])
def test_igtl_bad_data_raises(corrupt):
    data = bytearray(image_message(np.zeros((ROWS, COLS), np.uint8), np.eye(4), 1.0, "Image").pack())
    if corrupt == "crc":
        data[-1] ^= 0xFF
    else:
        data[42:50] = (1 << 40).to_bytes(8, "big")  # body size
    with socket.create_server(("127.0.0.1", 0)) as listener:
        listener.settimeout(HANG_GUARD_S)
        with IgtlSource("127.0.0.1", listener.getsockname()[1]) as source:
            connection, _ = listener.accept()
            with connection:
                connection.sendall(data)
                with pytest.raises(ImageSourceError, match="bad data"):
                    source.latest(timeout_s=5.0)


# --- OpenIGTLink out -------------------------------------------------------------------------


def test_publisher_received_by_a_plain_pyigtl_client():
    image_to_tool_rigid = make_transform(Rotation.from_euler("z", 5, degrees=True), [1.0, 2.0, 100.0])
    image_to_tool = image_to_tool_rigid @ np.diag([0.3, 0.25, 1.0, 1.0])
    tool_to_base = pose(4)
    image = np.random.default_rng(2).integers(0, 256, (ROWS, COLS), dtype=np.uint8)
    with IgtlPublisher(port=0) as publisher:
        assert publisher.publish_frame(image, tool_to_base, 1.0) == 0  # no client: nothing is sent
        publisher.publish_calibration(image_to_tool, timestamp=5.0)  # before the client connects
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", publisher.port)
        try:
            calibration = client.wait_for_message("ImageToProbe", timeout=HANG_GUARD_S)
            assert publisher.wait_for_client(HANG_GUARD_S)
            assert publisher.publish_frame(image, tool_to_base, 10.0, pose_timestamp=9.99) == 1
            frame = client.wait_for_message("Image", timeout=HANG_GUARD_S)
            probe = client.wait_for_message("ProbeToReference", timeout=HANG_GUARD_S)
        finally:
            client.stop()
    assert np.array_equal(calibration.matrix, image_to_tool.astype(np.float32)) and calibration.timestamp == 5.0
    assert frame.image.shape == (1, ROWS, COLS) and np.array_equal(frame.image[0], image)
    assert frame.world_coordinate_system == "ras"
    np.testing.assert_allclose(frame.ijk_to_world_matrix, tool_to_base @ image_to_tool, atol=1e-3)
    assert frame.timestamp == pytest.approx(10.0, abs=1e-6)
    assert np.array_equal(probe.matrix, tool_to_base.astype(np.float32))
    assert probe.timestamp == pytest.approx(9.99, abs=1e-6)


def test_publisher_does_not_block_on_a_client_that_never_reads():
    image = np.zeros((616, 820), np.uint8)
    with IgtlPublisher(port=0) as publisher, socket.create_connection(("127.0.0.1", publisher.port)):
        assert publisher.wait_for_client(HANG_GUARD_S)
        publishing = threading.Thread(
            target=lambda: [publisher.publish_frame(image, np.eye(4), float(i)) for i in range(100)], daemon=True
        )
        publishing.start()
        publishing.join(HANG_GUARD_S)
        assert not publishing.is_alive(), "publish_frame blocked on a stuck client"


def read_device_names(sock: socket.socket) -> list[str]:
    """Device names of the OpenIGTLink messages on ``sock`` until it has been idle for 0.5 s."""
    sock.settimeout(0.5)
    data = b""
    try:
        while chunk := sock.recv(1 << 20):
            data += chunk
    except TimeoutError:
        pass
    names, offset = [], 0
    while offset < len(data):
        header = pyigtl.MessageBase.parse_header(data[offset : offset + pyigtl.MessageBase.IGTL_HEADER_SIZE])
        names.append(header["device_name"])
        offset += pyigtl.MessageBase.IGTL_HEADER_SIZE + header["body_size"]
    return names


def test_publisher_never_drops_the_calibration_for_a_slow_client():
    image = np.zeros((616, 820), np.uint8)
    with IgtlPublisher(port=0) as publisher, socket.create_connection(("127.0.0.1", publisher.port)) as slow:
        assert publisher.wait_for_client(HANG_GUARD_S)
        for i in range(60):  # 30 MB: more than the socket buffers hold
            publisher.publish_frame(image, np.eye(4), float(i))
            if i == 40:  # queued behind frames that a slow client has not taken yet
                publisher.publish_calibration(np.diag([0.3, 0.25, 1.0, 1.0]))
        names = read_device_names(slow)
    assert "ImageToProbe" in names and names.count("Image") < 60


# --- Video and replay ------------------------------------------------------------------------


def test_video_file_frames_exact_then_end_of_stream(tmp_path):
    path = tmp_path / "clip.avi"
    frames = [f.image for f in make_frames(6, with_pose=False)]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 100.0, (COLS, ROWS), isColor=False)
    for image in frames:
        writer.write(image)
    writer.release()
    with VideoSource(str(path)) as source:
        got = list(source.frames(timeout_s=5.0))
        with pytest.raises(ImageSourceError, match=r"video:.*clip\.avi: end of stream"):
            source.latest(timeout_s=5.0)
    assert len(got) == len(frames) and all(np.array_equal(g.image, f) for g, f in zip(got, frames))
    assert [g.timestamp for g in got] == pytest.approx([i / 100.0 for i in range(len(frames))])


def test_video_bad_files(tmp_path):
    with pytest.raises(ImageSourceError, match=r"video:.*missing\.avi: no such video file"):
        VideoSource(str(tmp_path / "missing.avi")).open()
    junk = tmp_path / "junk.avi"
    junk.write_text("not a video")
    with pytest.raises(ImageSourceError, match=r"video:.*junk\.avi: cannot open"):
        VideoSource(str(junk)).open()


def write_session(path, n: int):
    with SessionWriter(path, Manifest(kind="calibration", pixel_spacing_mm=(0.3, 0.25))) as writer:
        for frame in make_frames(n, with_pose=True):
            writer.append(
                frame.image, frame.tool_to_base, timestamp=frame.timestamp - 0.04, pose_timestamp=frame.pose_timestamp
            )
    return load_session(path)


@pytest.mark.parametrize("rate_hz", [None, 200.0], ids=["recorded-timing", "given-rate"])
def test_replay_gives_the_recorded_frames_and_poses(tmp_path, rate_hz):
    session = write_session(tmp_path / "s", 5)
    with ReplaySource(tmp_path / "s", rate_hz=rate_hz) as source:
        got = list(source.frames(timeout_s=5.0))
        with pytest.raises(ImageSourceError, match="end of stream"):
            source.latest(timeout_s=1.0)
    assert [g.index for g in got] == list(range(5))
    for i, g in enumerate(got):
        record = session.records[i]
        assert np.array_equal(g.image, session.image(i)) and np.array_equal(g.tool_to_base, record.tool_to_base)
        assert (g.timestamp, g.pose_timestamp) == (record.timestamp, record.pose_timestamp)
        assert g.pixel_spacing_mm == (0.3, 0.25)


def test_replay_schedule_and_faults(tmp_path):
    session = write_session(tmp_path / "s", 3)
    assert replay_times(session.records, None) == pytest.approx([0.0, 0.05, 0.1])
    assert replay_times(session.records, 10.0) == pytest.approx([0.0, 0.1, 0.2])
    with pytest.raises(ImageSourceError, match=r"replay:.*nowhere: session folder not found"):
        ReplaySource(tmp_path / "nowhere").open()
    write_session(tmp_path / "long", 12)
    with ReplaySource(tmp_path / "long", rate_hz=1000.0, buffer_frames=3) as source:
        wait_until(lambda: not source._thread.is_alive(), "the replay's end")  # all 12 frames into 3 places
        with pytest.raises(ImageSourceError, match=r"\d+ frames dropped: the reader fell behind"):
            list(source.frames(timeout_s=5.0))


# --- Pose pairing ----------------------------------------------------------------------------


# --- Command line ----------------------------------------------------------------------------


def test_parse_image_spec_good():
    assert parse_image_spec("sim") is None
    igtl = parse_image_spec("igtl:127.0.0.1:18944")
    assert isinstance(igtl, IgtlSource) and (igtl.host, igtl.port) == ("127.0.0.1", 18944)
    assert igtl.name == "igtl:127.0.0.1:18944"
    assert isinstance(parse_image_spec("video:0"), VideoSource) and parse_image_spec("video:0").is_device
    assert parse_image_spec("video:clips/a.avi").name == "video:clips/a.avi"
    replay = parse_image_spec("replay:sessions/cal")
    assert isinstance(replay, ReplaySource) and str(replay.session_path) == "sessions/cal"


BAD_SPECS = ["", "simulator", "igtl", "igtl:host", "igtl::18944", "igtl:host:0", "igtl:host:70000", "igtl:host:x"]


@pytest.mark.parametrize("spec", [*BAD_SPECS, "video:", "replay:", "usb:0"])
def test_parse_image_spec_bad(spec):
    with pytest.raises(InputError) as error:
        parse_image_spec(spec)
    message = str(error.value)
    assert "\n" not in message and repr(spec) in message and "igtl:HOST:PORT" in message


@pytest.mark.parametrize("case, said, kept", [
    ("tiny spacing", "frame 0 states a pixel spacing of 1e-07 x 1e-07 mm, not two pixel sizes within", 0),
    ("huge spacing", "frame 0 states a pixel spacing of 1e+06 x 1e+06 mm", 0),
    ("nan spacing", "frame 0 states a pixel spacing of nan x nan mm", 0),
    ("size changes", "frame 3 is 30x20 px, the stream's frames 64x48: the scanner's settings changed", 3),
    ("spacing changes", "frame 3 states a pixel spacing of 0.2 x 0.25 mm, the stream's frames 0.3 x 0.25 mm", 3),
])
def test_igtl_live_values_are_checked_as_they_arrive(case, said, kept):
    """What a scanner states is held to the rules a session's reader applies, as it arrives: a
    sweep then stops at the frame that breaks them, with that reason, its frames kept."""
    frames = make_frames(6, False)
    spacing = {"tiny spacing": (1e-7, 1e-7), "huge spacing": (1e6, 1e6), "nan spacing": (np.nan, np.nan)}.get(case)
    if spacing is not None:
        frames = make_frames(6, False, spacing)
    elif case == "size changes":
        frames[3] = SourceFrame(np.zeros((20, 30), np.uint8), frames[3].timestamp, 3, None, None, (0.3, 0.25))
    else:
        frames[3] = SourceFrame(frames[3].image, frames[3].timestamp, 3, None, None, (0.2, 0.25))
    got = []
    with IgtlStreamer() as streamer, IgtlSource("127.0.0.1", streamer.port) as source:
        streamer.play(frames, rate_hz=200.0)
        with pytest.raises(ImageSourceError, match=re.escape(said)):
            for frame in source.frames(timeout_s=5.0):
                got.append(frame)
    assert len(got) == kept


class _Burst(ThreadedSource):
    """Emits ``n`` frames at once, as a flooding peer does."""

    def __init__(self, n: int):
        super().__init__("burst")
        self.n = n

    def _start(self) -> None:
        return None

    def _produce(self, handle, stop, emit) -> None:
        for i in range(self.n):
            emit(np.zeros((ROWS, COLS), np.uint8), float(i))

    def _release(self, handle) -> None:
        pass


def test_a_flood_that_outruns_the_reader_is_named_a_flood():
    """300 frames in a few milliseconds (far past 1000 frames/s) into a buffer of 256: the reader
    hears of the frames dropped, the stream's rate and that it is a flood."""
    with _Burst(BUFFER_FRAMES + 44) as source:
        wait_until(lambda: not source._thread.is_alive(), "the burst sent")
        with pytest.raises(ImageSourceError, match=r"44 frames dropped: the reader fell behind the stream "
                                                   r"\(\d+ frames/s\) by more than 256 frames: flooded"):
            next(source.frames(timeout_s=5.0))


def test_a_flood_is_named_a_flood():
    stream = StreamFormat("igtl:127.0.0.1:18944")
    image = np.zeros((ROWS, COLS), np.uint8)
    with pytest.raises(ImageSourceError, match="flooded: more than 1000 frames in a second"):
        for i in range(int(MAX_RATE_HZ) + 1):  # far faster than a second on any machine
            stream.check(SourceFrame(image, time.time(), i))
