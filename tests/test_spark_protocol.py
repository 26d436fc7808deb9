"""The Spark wire codec: the protocol sheet's frames byte for byte, and parser robustness."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.spark.protocol import (
    BASE_TO_HOST,
    CMD_FEEDBACK,
    CMD_QUERY,
    CMD_WHEEL_SPEED,
    HOST_TO_BASE,
    STOP_FRAME,
    VENDOR_QUERY,
    WELLFORMED_QUERY,
    Feedback,
    FrameParser,
    decode_feedback,
    decode_wheel_speed,
    encode_feedback,
    encode_frame,
    signed_delta32,
    twist_to_wheel_ticks,
    wheel_speed_frame,
)

SHEET_EXAMPLES = [
    ((0.0, 0.0), (0, 0), "53 4B 0C 00 18 00 00 00 00 C2 0D 0A"),
    ((0.2, 0.0), (692, 692), "53 4B 0C 00 18 B4 02 B4 02 2E 0D 0A"),
    ((-0.2, 0.0), (-692, -692), "53 4B 0C 00 18 4C FD 4C FD 54 0D 0A"),
    ((0.0, 1.0), (-460, 460), "53 4B 0C 00 18 34 FE CC 01 C1 0D 0A"),
]


@pytest.mark.parametrize(("twist", "ticks", "frame_hex"), SHEET_EXAMPLES)
def test_sheet_examples_byte_for_byte(twist, ticks, frame_hex):
    assert twist_to_wheel_ticks(*twist) == ticks
    assert wheel_speed_frame(*ticks) == bytes.fromhex(frame_hex)


def test_query_frames():
    assert WELLFORMED_QUERY == bytes.fromhex("53 4B 08 00 16 BC 0D 0A")
    assert VENDOR_QUERY == bytes.fromhex("53 4B 02 00 16 00 0D 0A")
    assert STOP_FRAME == bytes.fromhex(SHEET_EXAMPLES[0][2])


def test_clamp_applies_on_both_sides():
    # 1 m/s asks for 1000 mm/s per wheel; both signs clamp to 500 mm/s → trunc(500/0.28885) = 1731
    assert twist_to_wheel_ticks(1.0, 0.0) == (1731, 1731)
    assert twist_to_wheel_ticks(-1.0, 0.0) == (-1731, -1731)
    assert twist_to_wheel_ticks(0.0, -20.0) == (1731, -1731)


def test_non_finite_twist_is_refused():
    with pytest.raises(ValueError, match="finite"):
        twist_to_wheel_ticks(float("nan"), 0.0)


def test_host_side_parser_reads_both_queries_and_commands():
    parser = FrameParser(HOST_TO_BASE)
    frames = parser.feed(VENDOR_QUERY + WELLFORMED_QUERY + wheel_speed_frame(-460, 460))
    assert [(f.command, f.vendor_query) for f in frames] == [
        (CMD_QUERY, True), (CMD_QUERY, False), (CMD_WHEEL_SPEED, False),
    ]
    assert decode_wheel_speed(frames[2].payload) == (-460, 460)


def test_vendor_query_is_not_a_frame_for_the_host():
    parser = FrameParser(BASE_TO_HOST)
    assert parser.feed(VENDOR_QUERY) == []
    assert parser.rejected["length"] == 1


def _feedback(**kw) -> Feedback:
    base = {"cliff_bits": 0x3F, "bumper_bits": 0, "status_bits": 0, "dock_ir_bits": 0, "unused": 0,
                "encoder_10": 0xFFFFFFF0, "encoder_14": 12345, "base_time": 987654}
    imu = {"accel_g": (0.0, 0.0, 1.0), "gyro_dps": (0.0, 0.0, 12.5), "mag": (1.0, 2.0, 3.0),
               "rpy_deg": (0.5, -0.25, 170.0)}
    return Feedback(**{**base, **imu, **kw})


def test_feedback_round_trip_with_and_without_imu():
    with_imu = encode_feedback(_feedback())
    assert len(with_imu) == 73 and with_imu[2] == 73
    no_imu = encode_feedback(_feedback(accel_g=None, gyro_dps=None, mag=None, rpy_deg=None))
    assert len(no_imu) == 25
    frames = FrameParser(BASE_TO_HOST).feed(with_imu + no_imu)
    assert [f.command for f in frames] == [CMD_FEEDBACK, CMD_FEEDBACK]
    assert decode_feedback(frames[0].payload) == _feedback()
    assert decode_feedback(frames[1].payload).gyro_dps is None
    assert decode_feedback(frames[1].payload).encoder_10 == 0xFFFFFFF0


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda f: f[:-3] + bytes([(f[-3] + 1) & 0xFF]) + f[-2:], "checksum"),
        (lambda f: f[:-1] + b"\x0b", "trailer"),
        (lambda f: f[:2] + b"\x07" + f[3:], "length"),
        (lambda f: f[:2] + b"\x0c" + f[3:], "length"),  # a length feedback frames never have
        (lambda f: f[:3] + b"\x00\x42" + f[5:], "unknown_command"),
    ],
)
def test_rejections_are_counted_by_reason_and_the_next_frame_survives(mutate, reason):
    good = encode_feedback(_feedback())
    parser = FrameParser(BASE_TO_HOST)
    frames = parser.feed(mutate(good) + good)
    assert len(frames) == 1 and decode_feedback(frames[0].payload) == _feedback()
    assert parser.rejected[reason] >= 1


def test_truncated_frame_followed_by_good_frame_loses_only_the_truncated_one():
    good = encode_feedback(_feedback())
    parser = FrameParser(BASE_TO_HOST)
    assert len(parser.feed(good[:40] + good + good)) == 2


def test_signed_delta32_wraps():
    assert signed_delta32(5, 0xFFFFFFFB) == 10
    assert signed_delta32(0xFFFFFFFB, 5) == -10
    assert signed_delta32(100, 100) == 0


# --- properties --------------------------------------------------------------------------------

u32 = st.integers(0, 0xFFFFFFFF)
f32 = st.floats(-1000, 1000, allow_nan=False, width=32)
feedbacks = st.builds(
    Feedback,
    cliff_bits=st.integers(0, 255), bumper_bits=st.integers(0, 255),
    status_bits=st.integers(0, 255), dock_ir_bits=st.integers(0, 255), unused=st.integers(0, 255),
    encoder_10=u32, encoder_14=u32, base_time=u32,
    accel_g=st.tuples(f32, f32, f32), gyro_dps=st.tuples(f32, f32, f32),
    mag=st.tuples(f32, f32, f32), rpy_deg=st.tuples(f32, f32, f32),
)
good_frames = st.one_of(
    feedbacks.map(encode_feedback),
    feedbacks.map(lambda fb: encode_feedback(
        Feedback(fb.cliff_bits, fb.bumper_bits, fb.status_bits, fb.dock_ir_bits, fb.unused,
                 fb.encoder_10, fb.encoder_14, fb.base_time))),
)


@st.composite
def bad_frames(draw):
    """Noise of the kinds a serial line produces: random bytes, truncated or corrupted frames."""
    frame = draw(good_frames)
    kind = draw(st.sampled_from(["random", "truncated", "flipped", "header_only"]))
    if kind == "random":
        return draw(st.binary(min_size=1, max_size=80))
    if kind == "truncated":
        return frame[: draw(st.integers(1, len(frame) - 1))]
    if kind == "header_only":
        return b"SK" + draw(st.binary(max_size=4))
    i = draw(st.integers(0, len(frame) - 1))
    return frame[:i] + bytes([frame[i] ^ draw(st.integers(1, 255))]) + frame[i + 1 :]


def _chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    return [data[a:b] for a, b in zip([0, *points], [*points, len(data)])]


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=600), st.lists(st.integers(0, 10_000), max_size=20))
def test_no_byte_stream_raises(data, cuts):
    for accepted in (BASE_TO_HOST, HOST_TO_BASE):
        parser = FrameParser(accepted)
        for chunk in _chunked(data, cuts):
            parser.feed(chunk)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.tuples(st.lists(bad_frames(), max_size=3), good_frames), min_size=1, max_size=8),
    st.lists(st.integers(0, 10_000), max_size=30),
)
def test_every_good_frame_in_noise_is_recovered(pieces, cuts):
    stream = b"".join(b"".join(noise) + frame for noise, frame in pieces)
    expected = [frame for _, frame in pieces]
    parser = FrameParser(BASE_TO_HOST)
    got = []
    for chunk in _chunked(stream, cuts):
        got += parser.feed(chunk)
    got_bytes = [encode_frame(f.command, f.payload) for f in got]
    # every good frame comes back, in order; anything else it found is a frame that the noise
    # really spelled out byte for byte (noise pieces can join into one), never an invention
    remaining = iter(got_bytes)
    assert all(any(g == want for g in remaining) for want in expected)
    assert all(g in stream for g in got_bytes)
    assert len(got_bytes) >= len(expected)
