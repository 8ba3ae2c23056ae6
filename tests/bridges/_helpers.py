"""Shared helpers of the bridge tests: an ARKit-named example set, packet bytes, an OSC receiver."""

from __future__ import annotations

import argparse
import importlib
import queue
import struct
import threading

import numpy as np
from pythonosc.dispatcher import Dispatcher
from pythonosc.osc_server import BlockingOSCUDPServer

from facecast.rig import ExampleSet

#: A few ARKit shapes, in ARKit and in ICT spelling (browInnerUp split in halves).
SHAPES = ("eyeBlinkLeft", "JawOpen", "mouthSmile_L", "browInnerUp_L", "browInnerUp_R")


def arkit_example_set(k: int = 6, seed: int = 0) -> ExampleSet:
    """Neutral + 5 ARKit-named shapes on K random feature points; a small target strip."""
    rng = np.random.default_rng(seed)
    names = ("neutral", *SHAPES)
    m = len(names)
    source = np.repeat(rng.normal(size=(1, k, 3)), m, axis=0)
    source[1:] += rng.normal(scale=0.3, size=(m - 1, k, 3))
    target = np.repeat(rng.normal(size=(1, 12, 3)), m, axis=0)
    target[1:] += rng.normal(scale=0.3, size=(m - 1, 12, 3))
    faces = np.array([[i, i + 1, i + 2] for i in range(10)])
    return ExampleSet(names, source, target, faces)


def livelink_packet(
    values,
    *,
    device: bytes = b"0C0D3C5E-6F8A-4B1C-9D2E-3F4A5B6C7D8E",
    subject: bytes = b"iPhone",
    frame: int = 100,
    sub_frame: float = 0.25,
    rate: tuple[int, int] = (60, 1),
    count: int = 61,
) -> bytes:
    """A Live Link Face packet, field by field as the layout documents it."""
    out = bytearray()
    out += bytes([6])  # uint8 packet version
    out += struct.pack(">i", len(device)) + device  # int32 length + device id
    out += struct.pack(">i", len(subject)) + subject  # int32 length + subject name
    out += struct.pack(">i", frame)  # frame number
    out += struct.pack(">f", sub_frame)  # sub-frame
    out += struct.pack(">i", rate[0]) + struct.pack(">i", rate[1])  # frame rate
    out += bytes([count])  # uint8 value count
    for value in values:
        out += struct.pack(">f", value)  # big-endian float32 each
    return bytes(out)


def pylivelinkface_packet(
    values,
    *,
    device: bytes = b"$my-phone",
    subject: str = "Python_LiveLinkFace",
    frame: int = 7,
    sub_frame: float = 0.5,
    rate: tuple[int, int] = (60, 1),
) -> bytes:
    """A packet in PyLiveLinkFace's layout, field by field as livelink.py documents it.

    Version 6 as a little-endian uint32, the device id with no length before it, the
    subject name's length in characters (big-endian int32), then as the app's layout.
    An empty ``values`` ends the packet after the name (no face).
    """
    out = bytearray()
    out += struct.pack("<I", 6)  # uint32 little-endian version
    out += device  # "$" + id, no length
    out += struct.pack(">i", len(subject)) + subject.encode()  # length in characters
    if len(values):
        out += struct.pack(">ifii", frame, sub_frame, *rate)  # frame time
        out += bytes([61]) + struct.pack(">61f", *values)
    return bytes(out)


def run_command(module: str, argv: list[str]) -> int:
    """Run one command module's parser and ``func`` as ``facecast`` main does (errors raised).

    ``facecast.cli.main`` lists every command module; these run alone so the tests do
    not depend on the other commands being importable.
    """
    parser = argparse.ArgumentParser(prog="facecast")
    sub = parser.add_subparsers(dest="command", required=True)
    importlib.import_module(f"facecast.cli.commands.{module}").register(sub)
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


class OscReceiver:
    """python-osc's UDP server in a thread; every message it dispatches lands in a queue.

    The blocking server handles one datagram at a time, so the queue keeps their order.
    """

    def __init__(self) -> None:
        self.messages: queue.Queue[tuple[str, list]] = queue.Queue()
        dispatcher = Dispatcher()
        dispatcher.set_default_handler(
            lambda address, *args: self.messages.put((address, list(args)))
        )
        self.server = BlockingOSCUDPServer(("127.0.0.1", 0), dispatcher)
        self.address = self.server.server_address[:2]
        self._thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self._thread.start()

    def get(self, timeout: float = 10.0) -> tuple[str, list]:
        return self.messages.get(timeout=timeout)

    def until_apply(self, timeout: float = 10.0) -> list[tuple[str, list]]:
        """Messages up to and including the next ``/VMC/Ext/Blend/Apply``."""
        out = [self.get(timeout)]
        while out[-1][0] != "/VMC/Ext/Blend/Apply":
            out.append(self.get(timeout))
        return out

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self._thread.join(timeout=10)
