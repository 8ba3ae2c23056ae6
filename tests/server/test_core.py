"""The connection core without a socket: bytes and a clock in, bytes and decisions out.

In the style of websockets' tests/test_protocol.py: each test feeds encoded client
messages and clock readings to a core and asserts on the bytes it queues (decoded with
the client's own decoder) and on what it raises. No event loop, no server.
"""

from __future__ import annotations

import numpy as np
import pytest
from _server_helpers import frame_points, tiny_rig

from facecast.protocol import (
    Calibrate,
    Calibrated,
    Error,
    ErrorCode,
    Frame,
    Hello,
    Limits,
    Ping,
    Pong,
    ProtocolError,
    Ready,
    ServerProtocol,
    Smoothing,
    decode_server,
    encode,
)
from facecast.rig.errors import RigError
from facecast.server.connection.core import (
    CLOSE_GRACE,
    Closing,
    ConnectionCore,
    PublisherCore,
    StreamCore,
    WatcherCore,
)
from facecast.server.guards.frame_rate import ERROR_INTERVAL
from facecast.server.settings import Settings

IDLE = 5.0


@pytest.fixture(scope="module")
def rig():
    return tiny_rig()


def stream_core(now: float = 0.0, **settings: float) -> StreamCore:
    values = {"max_fps": 1000.0, "rate_burst": 100, "idle_timeout": IDLE, **settings}
    config = Settings(**values)  # type: ignore[arg-type]
    protocol = ServerProtocol(Limits(max_message_bytes=config.max_message_bytes))
    return StreamCore(protocol, config, now, idle_timeout=config.idle_timeout)


def sent(core: ConnectionCore) -> list[object]:
    """What the core queued for the client, decoded as the client would."""
    return [decode_server(data) for data in core.data_to_send()]


def opened(core: StreamCore, rig, now: float = 0.0, **hello: object) -> Ready:
    """Feed ``hello``, answer the rig load with ``rig``: the ``ready`` sent."""
    work = core.handle(core.receive(encode(Hello(rig="face", **hello)), now), now)  # type: ignore[arg-type]
    assert isinstance(work, Hello)
    core.open(core.bind(rig), now, "s1")
    (ready,) = sent(core)
    assert isinstance(ready, Ready)
    return ready


def frame_bytes(rig, seq: int) -> bytes:
    return encode(Frame(seq=seq, ts=seq / 60, points=frame_points(rig, seq)))


# -- hello and ready ---------------------------------------------------------------------
def test_hello_asks_for_its_rig_and_open_sends_ready_with_the_limits(rig):
    core = stream_core(max_fps=30.0, rate_burst=4)
    work = core.handle(core.receive(encode(Hello(rig="face", output="weights")), 0.0), 0.0)

    assert isinstance(work, Hello) and work.rig == "face"
    assert core.data_to_send() == []  # nothing is said before the rig is there
    core.open(core.bind(rig), 0.1, "s1")
    (ready,) = sent(core)
    assert isinstance(ready, Ready)
    assert (ready.session, ready.rig, ready.num_points) == ("s1", "face", rig.num_points)
    assert ready.limits["max_fps"] == 30.0 and ready.limits["rate_burst"] == 4
    assert ready.limits["idle_timeout"] == IDLE


def test_hello_with_an_invalid_rig_id_is_fatal_unknown_rig():
    core = stream_core()
    message = core.receive(encode(Hello(rig="../etc")), 0.0)

    with pytest.raises(ProtocolError) as caught:
        core.handle(message, 0.0)
    assert caught.value.code is ErrorCode.UNKNOWN_RIG and caught.value.fatal


def test_frame_before_hello_closes_with_wrong_state_and_its_close_code(rig):
    core = stream_core()
    with pytest.raises(ProtocolError) as caught:
        core.receive(frame_bytes(rig, 0), 0.0)

    with pytest.raises(Closing) as closing:
        core.report(caught.value)
    assert caught.value.code is ErrorCode.WRONG_STATE
    assert (closing.value.code, closing.value.reason) == (1008, "wrong_state")
    error = decode_server(core.closing_bytes(closing.value))
    assert isinstance(error, Error) and error.fatal and error.code is ErrorCode.WRONG_STATE


def test_text_message_is_fatal_before_hello_and_an_error_after(rig):
    before = stream_core()
    with pytest.raises(ProtocolError) as caught:
        before.receive_text("hi", 0.0)
    assert caught.value.code is ErrorCode.TEXT_NOT_SUPPORTED and caught.value.fatal

    after = stream_core()
    opened(after, rig)
    with pytest.raises(ProtocolError) as caught:
        after.receive_text("hi", 0.0)
    after.report(caught.value)
    (error,) = sent(after)
    assert isinstance(error, Error) and not error.fatal
    assert error.code is ErrorCode.TEXT_NOT_SUPPORTED


def test_ping_is_answered_with_its_id_and_ts_and_the_servers_clock_even_before_hello():
    core = stream_core()
    core.wall_clock = lambda: 1_700_000_000.5
    assert core.handle(core.receive(encode(Ping(id=7, ts=1.5)), 0.0), 0.0) is None

    assert sent(core) == [Pong(id=7, ts=1.5, server_ts=1_700_000_000.5)]


def test_bind_with_align_scale_leaves_the_given_rig_unchanged(rig):
    core = stream_core()
    core.handle(core.receive(encode(Hello(rig="face", align=True, align_scale=True)), 0.0), 0.0)

    bound = core.bind(rig)
    assert bound is not rig and bound.align_scale
    assert not rig.align_scale
    points = frame_points(rig, 2)
    bigger = points.mean(axis=0) + 1.5 * (points - points.mean(axis=0))
    np.testing.assert_allclose(
        bound.weights(bigger, align=True), bound.weights(points, align=True), atol=1e-6
    )
    assert not np.allclose(rig.weights(bigger, align=True), rig.weights(points, align=True))


# -- frames and the rate limit -----------------------------------------------------------
def test_frames_within_the_rate_pass_and_their_result_carries_no_drop(rig):
    core = stream_core()
    opened(core, rig)
    frame = core.receive(frame_bytes(rig, 0), 0.01)

    assert isinstance(frame, Frame) and core.frame_allowed(frame, 0.01)
    values = rig.weights(frame.points).astype(np.float32)
    result = decode_server(core.result(frame, values, "weights", 12))
    assert (result.seq, result.dropped, result.proc_us) == (0, 0, 12)
    assert core.counters.frames_in == 1


def test_frame_over_the_rate_is_dropped_and_told_once_per_interval(rig):
    core = stream_core(max_fps=10.0, rate_burst=2)
    opened(core, rig)
    allowed = [core.frame_allowed(core.receive(frame_bytes(rig, s), 0.0), 0.0) for s in range(5)]

    assert allowed == [True, True, False, False, False]
    (error,) = sent(core)  # one RATE_LIMITED for the first drop, none for the next two
    assert isinstance(error, Error) and error.code is ErrorCode.RATE_LIMITED
    assert (error.seq, error.dropped, error.fatal) == (2, 1, False)
    assert core.counters.dropped_rate == 3


def test_drops_after_the_last_error_are_reported_at_the_deadline(rig):
    core = stream_core(max_fps=10.0, rate_burst=1, idle_timeout=60.0)
    opened(core, rig)
    for seq in range(3):
        core.frame_allowed(core.receive(frame_bytes(rig, seq), 0.0), 0.0)
    sent(core)  # the first error (dropped 1)

    assert core.deadline() == pytest.approx(ERROR_INTERVAL)
    core.tick(ERROR_INTERVAL - 0.01)
    assert sent(core) == []
    core.tick(ERROR_INTERVAL)
    (late,) = sent(core)
    assert isinstance(late, Error) and (late.seq, late.dropped) == (2, 2)
    assert core.deadline() == pytest.approx(60.0)  # only the idle rule is left


def test_no_late_error_when_a_result_already_carried_the_total(rig):
    core = stream_core(max_fps=10.0, rate_burst=1)
    opened(core, rig)
    frames = [core.receive(frame_bytes(rig, s), 0.0) for s in range(3)]
    [core.frame_allowed(f, 0.0) for f in frames]
    sent(core)
    passed = core.receive(frame_bytes(rig, 3), 0.5)
    assert core.frame_allowed(passed, 0.5)
    values = rig.weights(passed.points).astype(np.float32)

    assert decode_server(core.result(passed, values, "weights", 1)).dropped == 2
    core.tick(ERROR_INTERVAL)
    assert sent(core) == []


def test_result_that_is_not_finite_is_refused_for_that_frame_only(rig):
    core = stream_core()
    opened(core, rig)
    frame = core.receive(frame_bytes(rig, 0), 0.0)
    core.frame_allowed(frame, 0.0)

    values = np.full(rig.num_examples, np.nan, dtype=np.float32)
    with pytest.raises(ProtocolError) as caught:
        core.result(frame, values, "weights", 1)
    assert caught.value.code is ErrorCode.RESULT_NOT_FINITE and not caught.value.fatal


def test_frame_with_the_wrong_point_count_is_an_error_not_a_close(rig):
    core = stream_core()
    opened(core, rig)
    data = encode(Frame(seq=3, ts=0.0, points=np.zeros((rig.num_points + 1, 3), np.float32)))

    with pytest.raises(ProtocolError) as caught:
        core.receive(data, 0.0)
    core.report(caught.value)
    (error,) = sent(core)
    assert (error.code, error.seq, error.fatal) == (ErrorCode.WRONG_POINT_COUNT, 3, False)


# -- idle --------------------------------------------------------------------------------
def test_idle_timeout_closes_after_no_message_for_idle_timeout(rig):
    core = stream_core()
    opened(core, rig)
    core.receive(encode(Ping(id=1, ts=0.0)), 2.0)

    assert core.deadline() == pytest.approx(2.0 + IDLE)
    core.tick(2.0 + IDLE - 0.001)
    with pytest.raises(Closing) as closing:
        core.tick(2.0 + IDLE)
    assert (closing.value.code, closing.value.reason) == (1008, "idle timeout")
    assert closing.value.error is not None
    assert closing.value.error.code is ErrorCode.IDLE_TIMEOUT


def test_time_loading_the_rig_for_hello_is_not_client_idle_time(rig):
    core = stream_core()
    work = core.handle(core.receive(encode(Hello(rig="face")), 0.0), 0.0)
    assert isinstance(work, Hello)

    # The load takes longer than the idle timeout: no deadline while it runs.
    assert core.deadline() is None
    core.tick(IDLE + 2.0)
    core.open(core.bind(rig), IDLE + 3.0, "s1")
    assert core.deadline() == pytest.approx(2 * IDLE + 3.0)
    core.tick(2 * IDLE + 2.9)
    assert isinstance(sent(core)[0], Ready)
    with pytest.raises(Closing):
        core.tick(2 * IDLE + 3.0)


def test_time_fitting_a_calibrate_message_is_not_client_idle_time(rig):
    core = stream_core()
    opened(core, rig)
    points = frame_points(rig, 0)
    work = core.handle(core.receive(encode(Calibrate(points=points)), 1.0), 1.0)
    assert isinstance(work, Calibrate)

    assert core.deadline() is None
    core.tick(1.0 + IDLE)
    core.calibrated(rig.calibrated(points), 1.0 + IDLE + 1.0)
    assert core.deadline() == pytest.approx(1.0 + 2 * IDLE + 1.0)


def test_a_failed_rig_load_ends_the_wait():
    core = stream_core()
    core.handle(core.receive(encode(Hello(rig="face")), 0.0), 0.0)

    core.failed(1.0)
    assert core.deadline() == pytest.approx(1.0 + IDLE)


def test_watcher_has_no_idle_rule_and_may_only_ping(rig):
    hello = Hello(rig="face")
    core = WatcherCore(ServerProtocol(hello=hello), Settings(idle_timeout=1.0), 0.0)

    assert core.deadline() is None
    core.tick(1e6)
    with pytest.raises(ProtocolError) as caught:
        core.receive(frame_bytes(rig, 0), 0.0)
    assert caught.value.code is ErrorCode.WRONG_STATE and not caught.value.fatal


# -- calibration -------------------------------------------------------------------------
def test_calibrate_with_points_asks_for_the_fit_and_acks_it(rig):
    core = stream_core()
    opened(core, rig)
    points = frame_points(rig, 1)
    work = core.handle(core.receive(encode(Calibrate(points=points)), 0.0), 0.0)

    assert isinstance(work, Calibrate) and np.array_equal(work.points, points)
    assert work.noise is None
    calibrated = rig.calibrated(work.points)
    core.calibrated(calibrated, 0.1)
    assert core.rig is calibrated and core.base_rig is rig
    assert sent(core) == [Calibrated(active=True)]


def test_calibrate_without_points_takes_the_next_frame_once(rig):
    core = stream_core()
    opened(core, rig)
    assert core.handle(core.receive(encode(Calibrate()), 0.0), 0.0) is None

    assert core.take_neutral()
    assert not core.take_neutral()
    core.calibrated(rig.calibrated(frame_points(rig, 0)), 0.1, seq=9)
    assert sent(core) == [Calibrated(active=True, seq=9)]


def test_calibrate_noise_comes_with_its_points_or_waits_with_the_next_frame(rig):
    core = stream_core()
    opened(core, rig)
    points = frame_points(rig, 1)

    work = core.handle(core.receive(encode(Calibrate(points=points, noise=0.02)), 0.0), 0.0)
    assert isinstance(work, Calibrate) and work.noise == 0.02
    core.calibrated(rig.calibrated(points), 0.1)
    assert core.handle(core.receive(encode(Calibrate(noise=0.03)), 0.2), 0.2) is None

    assert core.take_neutral() and core.calibrate_noise == 0.03


def test_calibrate_reset_goes_back_to_the_rig_of_hello(rig):
    core = stream_core()
    opened(core, rig, calibration=True)
    assert core.calibrate_next  # hello asked for it
    core.calibrated(rig.calibrated(frame_points(rig, 0)), 0.0, seq=0)
    sent(core)

    core.handle(core.receive(encode(Calibrate(reset=True)), 1.0), 1.0)
    assert core.rig is rig and not core.calibrate_next
    assert sent(core) == [Calibrated(active=False)]


def test_refused_calibration_is_calibration_failed_not_a_close(rig):
    core = stream_core()
    opened(core, rig)
    core.handle(core.receive(encode(Calibrate(points=frame_points(rig, 0))), 0.0), 0.0)

    core.calibration_failed(RigError("neutral too far"), 0.5)
    (error,) = sent(core)
    assert isinstance(error, Error) and error.code is ErrorCode.CALIBRATION_FAILED
    assert not error.fatal and "neutral too far" in error.message
    assert core.deadline() == pytest.approx(0.5 + IDLE)


def test_calibrates_over_the_budget_are_refused_and_the_budget_refills(rig):
    core = stream_core(calibrate_rate=2.0, calibrate_burst=2)
    opened(core, rig)
    points = frame_points(rig, 1)
    asked = [core.handle(core.receive(encode(Calibrate(points=points)), 0.0), 0.0)
             for _ in range(3)]  # fmt: skip

    assert [isinstance(work, Calibrate) for work in asked] == [True, True, False]
    (error,) = sent(core)
    assert isinstance(error, Error) and error.code is ErrorCode.RATE_LIMITED
    assert error.seq is None and not error.fatal and "2 calibrations/s" in error.message
    assert core.rig is rig  # nothing changed
    # Half a second later one token is back (2/s).
    assert isinstance(core.handle(core.receive(encode(Calibrate(points=points)), 0.5), 0.5),
                      Calibrate)  # fmt: skip


def test_a_reset_is_never_refused(rig):
    core = stream_core(calibrate_rate=0.001, calibrate_burst=1)
    opened(core, rig)
    for _ in range(3):
        core.handle(core.receive(encode(Calibrate(reset=True)), 0.0), 0.0)

    assert sent(core) == [Calibrated(active=False)] * 3


# -- closing -----------------------------------------------------------------------------
def test_closing_without_an_error_sends_only_the_close():
    core = stream_core()
    ending = Closing(1001, "server shutting down")

    assert core.closing_bytes(ending) is None
    assert CLOSE_GRACE > 0


def test_internal_failure_closes_1011_with_a_fatal_internal_error():
    core = stream_core()
    ending = Closing.internal()

    error = decode_server(core.closing_bytes(ending))
    assert ending.code == 1011
    assert isinstance(error, Error) and error.code is ErrorCode.INTERNAL and error.fatal


def test_errors_are_counted_and_named_for_the_metrics(rig):
    core = stream_core(max_fps=10.0, rate_burst=1)
    names: list[str] = []
    core.on_error = names.append
    opened(core, rig)
    for seq in range(2):
        core.frame_allowed(core.receive(frame_bytes(rig, seq), 0.0), 0.0)

    with pytest.raises(Closing):
        core.tick(IDLE)
    assert names == ["RATE_LIMITED", "IDLE_TIMEOUT"]
    assert core.counters.errors == 2


# -- the channel publisher ---------------------------------------------------------------
def publisher_core() -> PublisherCore:
    return PublisherCore(ServerProtocol(), Settings(), 0.0, idle_timeout=IDLE)


def test_publisher_refuses_outputs_a_channel_does_not_serve():
    core = publisher_core()
    message = core.receive(encode(Hello(rig="face", output="moving")), 0.0)

    with pytest.raises(ProtocolError) as caught:
        core.handle(message, 0.0)
    assert caught.value.code is ErrorCode.INVALID_FIELD and caught.value.fatal


def test_publisher_dropped_total_counts_frames_the_channel_superseded(rig):
    core = PublisherCore(
        ServerProtocol(), Settings(max_fps=10.0, rate_burst=1), 0.0, idle_timeout=IDLE
    )
    core.superseded = lambda: 4
    core.handle(core.receive(encode(Hello(rig="face")), 0.0), 0.0)
    core.open(rig, 0.0, "p1")
    sent(core)
    for seq in range(2):
        core.frame_allowed(core.receive(frame_bytes(rig, seq), 0.0), 0.0)

    (error,) = sent(core)
    assert error.dropped == 5 and core.dropped_total() == 5


def test_publisher_neutral_is_captured_renamed_and_reset(rig):
    core = publisher_core()
    core.handle(core.receive(encode(Hello(rig="face")), 0.0), 0.0)
    core.open(rig, 0.0, "p1")
    points = frame_points(rig, 2)

    core.calibrated(rig.calibrated(points), 0.0, seq=1, points=points)
    first = core.neutral_id
    core.calibrated(rig.calibrated(points), 0.0, seq=2, points=points)
    assert np.array_equal(core.neutral, points) and first and core.neutral_id != first
    core.handle(core.receive(encode(Calibrate(reset=True)), 1.0), 1.0)
    assert core.neutral is None and core.neutral_id == "" and core.rig is rig


def test_smoothing_options_go_to_the_filter_of_their_target(rig):
    points = Smoothing(target="points", min_cutoff=1.0, beta=0.5)
    weights = Smoothing(target="weights")
    stream = stream_core()
    opened(stream, rig, smoothing=weights)

    smoother = stream.smoother(rig)
    assert smoother is not None and smoother.target == "weights"
    assert smoother.filter.min_cutoff == weights.min_cutoff
    publisher = publisher_core()
    publisher.handle(publisher.receive(encode(Hello(rig="face", smoothing=points)), 0.0), 0.0)
    assert publisher.point_filter(rig) is not None and publisher.channel_smoothing is None
    publisher = publisher_core()
    publisher.handle(publisher.receive(encode(Hello(rig="face", smoothing=weights)), 0.0), 0.0)
    assert publisher.point_filter(rig) is None and publisher.channel_smoothing == weights


def test_no_smoothing_without_the_option(rig):
    core = stream_core()
    opened(core, rig)

    assert core.smoother(rig) is None and core.smoothing(rig) is None


def test_a_kalman_filter_on_a_rig_without_noise_is_refused_before_ready(rig):
    core = stream_core()
    core.handle(
        core.receive(encode(Hello(rig="face", smoothing=Smoothing(filter="kalman"))), 0.0), 0.0
    )

    with pytest.raises(ProtocolError) as refused:
        core.smoother(rig)  # the driver builds it before ``open``, which sends ready
    assert (refused.value.code, refused.value.fatal) == (ErrorCode.INVALID_FIELD, True)
