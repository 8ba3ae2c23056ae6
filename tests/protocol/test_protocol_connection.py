"""Session state machines and transport helpers (PROTOCOL.md §2, §9)."""

from __future__ import annotations

import numpy as np
import pytest
from _protocol_samples import SAMPLES
from _protocol_wire import pack

from facecast.protocol import (
    Calibrate,
    Calibrated,
    ClientProtocol,
    ClientState,
    Error,
    ErrorCode,
    FaceLost,
    Frame,
    Hello,
    Ping,
    Pong,
    ProtocolError,
    Result,
    ServerProtocol,
    ServerState,
    bearer_token,
    close_code,
    decode_server,
    encode,
    select_subprotocol,
    watch_hello,
)

HELLO = encode(Hello(rig="demo"))
READY = SAMPLES["ready"]  # K=2, M=3, weights f32


def _frame(k: int = 2, seq: int = 1) -> bytes:
    return encode(Frame(seq=seq, ts=0.0, points=np.zeros((k, 3), np.float32)))


def _raises(code: ErrorCode, call, *args) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        call(*args)
    assert info.value.code == code
    return info.value


def _open_server() -> ServerProtocol:
    server = ServerProtocol()
    server.receive(HELLO)
    server.send(READY)
    return server


# --- ServerProtocol ---------------------------------------------------------------------


def test_server_starts_awaiting_hello_and_streams_after_it() -> None:
    server = ServerProtocol()
    assert server.state is ServerState.AWAITING_HELLO
    message = server.receive(HELLO)
    assert message == Hello(rig="demo")
    assert server.state is ServerState.STREAMING
    assert server.hello == message


def test_frame_before_hello_is_fatal_wrong_state_with_seq() -> None:
    error = _raises(ErrorCode.WRONG_STATE, ServerProtocol().receive, _frame(seq=5))
    assert error.fatal
    assert error.seq == 5


def test_calibrate_before_hello_is_fatal_wrong_state() -> None:
    error = _raises(ErrorCode.WRONG_STATE, ServerProtocol().receive, encode(Calibrate()))
    assert error.fatal


def test_ping_before_hello_is_allowed() -> None:
    server = ServerProtocol()
    assert server.receive(encode(Ping(id=1, ts=0.0))) == Ping(id=1, ts=0.0)
    assert server.state is ServerState.AWAITING_HELLO


def test_second_hello_is_non_fatal_wrong_state() -> None:
    server = _open_server()
    error = _raises(ErrorCode.WRONG_STATE, server.receive, HELLO)
    assert not error.fatal
    assert server.state is ServerState.STREAMING


def test_bad_message_before_hello_is_fatal() -> None:
    error = _raises(ErrorCode.MALFORMED, ServerProtocol().receive, b"\xc1")
    assert error.fatal


def test_bad_frame_while_streaming_is_not_fatal() -> None:
    error = _raises(ErrorCode.MALFORMED, _open_server().receive, b"\xc1")
    assert not error.fatal


def test_unsupported_version_is_always_fatal() -> None:
    data = pack({"v": 2, "type": "frame"})
    assert _raises(ErrorCode.UNSUPPORTED_VERSION, _open_server().receive, data).fatal


def test_frame_with_wrong_point_count_after_ready_is_rejected_with_seq() -> None:
    error = _raises(ErrorCode.WRONG_POINT_COUNT, _open_server().receive, _frame(k=3, seq=9))
    assert error.seq == 9
    assert not error.fatal


def test_calibrate_with_wrong_point_count_is_rejected() -> None:
    data = encode(Calibrate(points=np.zeros((1, 3), np.float32)))
    _raises(ErrorCode.WRONG_POINT_COUNT, _open_server().receive, data)


def test_calibrate_with_rig_point_count_is_accepted() -> None:
    data = encode(Calibrate(points=np.zeros((2, 3), np.float32)))
    assert _open_server().receive(data).points.shape == (2, 3)


def test_frame_with_rig_point_count_is_accepted() -> None:
    assert _open_server().receive(_frame(k=2)).points.shape == (2, 3)


def test_text_before_hello_is_fatal_text_not_supported() -> None:
    assert _raises(ErrorCode.TEXT_NOT_SUPPORTED, ServerProtocol().receive_text, "hi").fatal


def test_text_while_streaming_is_not_fatal() -> None:
    assert not _raises(ErrorCode.TEXT_NOT_SUPPORTED, _open_server().receive_text, "hi").fatal


def test_server_cannot_send_ready_before_hello() -> None:
    _raises(ErrorCode.WRONG_STATE, ServerProtocol().send, READY)


def test_server_cannot_send_ready_twice() -> None:
    _raises(ErrorCode.WRONG_STATE, _open_server().send, READY)


def test_server_cannot_send_result_before_ready() -> None:
    server = ServerProtocol()
    server.receive(HELLO)
    _raises(ErrorCode.WRONG_STATE, server.send, SAMPLES["result"])


def test_server_cannot_send_a_computed_result_before_ready() -> None:
    server = ServerProtocol()
    server.receive(HELLO)
    result = SAMPLES["result"]
    _raises(
        ErrorCode.WRONG_STATE,
        lambda: server.send_result(
            result.seq, result.ts, result.values, output=result.output, proc_us=1, dropped=0
        ),
    )


@pytest.mark.parametrize(
    "values",
    [
        np.array([1.0, np.inf, 0.0], np.float16),  # what 7e4 becomes in f16
        np.array([1.0, np.nan, 0.0], np.float32),
        np.full((300,), np.inf, np.float16),  # the bit-test path of all_finite
    ],
    ids=["f16-overflow", "nan", "many-f16"],
)
def test_server_refuses_to_send_a_non_finite_result_and_stays_open(values) -> None:
    server = _open_server()

    error = _raises(
        ErrorCode.RESULT_NOT_FINITE,
        lambda: server.send_result(5, 0.0, values, output="weights", proc_us=1, dropped=0),
    )
    _raises(
        ErrorCode.RESULT_NOT_FINITE,
        server.send,
        Result(seq=6, ts=0.0, weights=values),
    )
    assert (error.seq, error.fatal) == (5, False)
    assert server.state is ServerState.STREAMING
    server.send_result(7, 0.0, np.ones(3, np.float32), output="weights", proc_us=1, dropped=0)


def test_fatal_error_closes_the_server_session() -> None:
    server = ServerProtocol()
    data = server.fail(ProtocolError(ErrorCode.UNKNOWN_RIG, "no rig 'x'", fatal=True))
    assert decode_server(data) == Error(
        code=ErrorCode.UNKNOWN_RIG, message="no rig 'x'", fatal=True
    )
    assert server.state is ServerState.CLOSED
    _raises(ErrorCode.WRONG_STATE, server.receive, HELLO)


def test_non_fatal_error_keeps_the_session_open() -> None:
    server = _open_server()
    server.fail(ProtocolError(ErrorCode.NON_FINITE, "nan", seq=3))
    assert server.state is ServerState.STREAMING


def test_pre_negotiated_session_starts_streaming() -> None:
    server = ServerProtocol(hello=Hello(rig="demo"))
    assert server.state is ServerState.STREAMING
    assert decode_server(server.send(READY)) == READY


def test_watcher_may_only_ping() -> None:
    server = ServerProtocol(hello=Hello(rig="demo"))
    server.send(READY)
    assert server.receive(encode(Ping(id=2, ts=0.0))) == Ping(id=2, ts=0.0)
    assert not _raises(ErrorCode.WRONG_STATE, server.receive, _frame()).fatal


def test_closed_server_refuses_to_send() -> None:
    server = _open_server()
    server.close()
    _raises(ErrorCode.WRONG_STATE, server.send, SAMPLES["result"])


# --- ClientProtocol ---------------------------------------------------------------------


def _open_client() -> ClientProtocol:
    client = ClientProtocol()
    client.send(Hello(rig="demo"))
    client.receive(encode(READY))
    return client


def test_client_streams_after_ready() -> None:
    client = _open_client()
    assert client.state is ClientState.STREAMING
    assert client.ready == READY


def test_client_cannot_send_frame_before_ready() -> None:
    client = ClientProtocol()
    client.send(Hello(rig="demo"))
    _raises(ErrorCode.WRONG_STATE, client.send, Frame(seq=0, ts=0.0, points=np.zeros((2, 3))))


def test_client_cannot_send_hello_twice() -> None:
    _raises(ErrorCode.WRONG_STATE, _open_client().send, Hello(rig="demo"))


def test_client_rejects_ready_before_hello() -> None:
    _raises(ErrorCode.WRONG_STATE, ClientProtocol().receive, encode(READY))


def test_client_rejects_second_ready() -> None:
    _raises(ErrorCode.WRONG_STATE, _open_client().receive, encode(READY))


def test_client_rejects_result_before_ready() -> None:
    client = ClientProtocol()
    client.send(Hello(rig="demo"))
    _raises(ErrorCode.WRONG_STATE, client.receive, encode(SAMPLES["result"]))


def test_client_accepts_result_matching_ready() -> None:
    assert _open_client().receive(encode(SAMPLES["result"])) == SAMPLES["result"]


@pytest.mark.parametrize(
    "result",
    [
        Result(seq=1, ts=0.0, weights=np.zeros(4, np.float32)),
        Result(seq=1, ts=0.0, weights=np.zeros(3, np.float16)),
        Result(seq=1, ts=0.0, vertices=np.zeros((4, 3), np.float32)),
    ],
    ids=["wrong-M", "wrong-dtype", "wrong-output"],
)
def test_client_rejects_result_not_matching_ready(result: Result) -> None:
    error = _raises(ErrorCode.INVALID_FIELD, _open_client().receive, encode(result))
    assert error.seq == 1


def test_client_accepts_events_while_streaming() -> None:
    client = _open_client()
    for message in (Calibrated(active=False), FaceLost(since=1.0), Pong(id=1, ts=0.0)):
        assert client.receive(encode(message)) == message


def test_fatal_error_closes_the_client_session() -> None:
    client = _open_client()
    client.receive(encode(Error(code=ErrorCode.IDLE_TIMEOUT, message="idle", fatal=True)))
    assert client.state is ClientState.CLOSED
    _raises(ErrorCode.WRONG_STATE, client.send, Ping(id=1, ts=0.0))


def test_watching_client_opens_on_ready_without_hello() -> None:
    client = ClientProtocol(watching=True)
    client.receive(encode(READY))
    assert client.state is ClientState.STREAMING
    _raises(ErrorCode.WRONG_STATE, client.send, Hello(rig="demo"))


def test_client_and_server_machines_talk_to_each_other() -> None:
    client, server = ClientProtocol(), ServerProtocol()
    server.receive(client.send(Hello(rig="demo", output="weights")))
    client.receive(server.send(READY))
    frame = server.receive(client.send(Frame(seq=4, ts=1.5, points=np.ones((2, 3)))))
    weights = np.array([1.0, 0.0, 0.0], np.float32)
    result = client.receive(server.send(Result(seq=frame.seq, ts=frame.ts, weights=weights)))
    assert (result.seq, result.ts) == (4, 1.5)
    np.testing.assert_array_equal(result.weights, weights)


# --- transport helpers ------------------------------------------------------------------


def test_bearer_token_from_authorization_header() -> None:
    assert bearer_token(authorization="Bearer abc.123") == "abc.123"


def test_bearer_scheme_is_case_insensitive() -> None:
    assert bearer_token(authorization="bearer abc") == "abc"


@pytest.mark.parametrize("header", ["Basic abc", "Bearer", "Bearer  ", "abc"])
def test_malformed_authorization_header_is_unauthorized(header: str) -> None:
    assert _raises(ErrorCode.UNAUTHORIZED, lambda: bearer_token(authorization=header)).fatal


def test_bearer_token_from_subprotocol() -> None:
    offered = ["facecast.v1", "facecast.bearer.tok-1"]
    assert bearer_token(subprotocols=offered) == "tok-1"


def test_bearer_token_from_query() -> None:
    assert bearer_token(query_token="q") == "q"


def test_header_wins_over_subprotocol_and_query() -> None:
    token = bearer_token(
        authorization="Bearer h", subprotocols=["facecast.bearer.s"], query_token="q"
    )
    assert token == "h"


def test_no_token_presented_gives_none() -> None:
    assert bearer_token(subprotocols=["facecast.v1", "facecast.bearer."]) is None


def test_server_selects_v1_never_the_bearer_subprotocol() -> None:
    assert select_subprotocol(["facecast.bearer.secret", "facecast.v1"]) == "facecast.v1"
    assert select_subprotocol(["facecast.bearer.secret"]) is None


def test_watch_query_gives_hello_with_defaults() -> None:
    assert watch_hello({"rig": "demo"}) == Hello(rig="demo", output="weights", dtype="f32")
    assert watch_hello({"rig": "d", "output": "vertices", "dtype": "f16"}).dtype == "f16"


@pytest.mark.parametrize("query", [{}, {"rig": ""}, {"rig": "d", "output": "x"}])
def test_bad_watch_query_is_fatal_invalid_field(query: dict) -> None:
    assert _raises(ErrorCode.INVALID_FIELD, watch_hello, query).fatal


@pytest.mark.parametrize(
    ("code", "close"),
    [
        (ErrorCode.MESSAGE_TOO_LARGE, 1009),
        (ErrorCode.TEXT_NOT_SUPPORTED, 1003),
        (ErrorCode.INTERNAL, 1011),
        (ErrorCode.OVERLOADED, 1013),
        (ErrorCode.WRONG_STATE, 1008),
        (4242, 1008),
    ],
)
def test_close_code_for_fatal_error(code: int, close: int) -> None:
    assert close_code(ProtocolError(code, "x", fatal=True)) == close
