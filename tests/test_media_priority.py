"""Teleop keeps priority over video on a shared radio (issue 28): the NavCam's packets carry
DSCP AF41, the velocity stream's EF, which a Wi-Fi link (WMM) queues ahead."""

from __future__ import annotations

import asyncio
import socket

from conftest import wait_until

from brasidas.media.video import VIDEO_DSCP, VideoOut, VideoSettings
from stationd.teleop import VELOCITY_TOS, _expedite


def _tos_receiver() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_RECVTOS, 1)
    sock.setblocking(False)
    return sock


def _received_tos(sock: socket.socket) -> set[int]:
    marks: set[int] = set()
    while True:
        try:
            _data, ancillary, _flags, _address = sock.recvmsg(65536, socket.CMSG_SPACE(1))
        except BlockingIOError:
            return marks
        for level, kind, value in ancillary:
            if level == socket.IPPROTO_IP and kind == socket.IP_TOS:
                marks.add(value[0])


async def test_video_is_af41_and_velocity_ef() -> None:
    video = _tos_receiver()
    stream = VideoOut("navcam", VideoSettings(test_source=True, port=video.getsockname()[1]))
    marks: set[int] = set()
    try:
        await stream.start()

        def marked() -> bool:
            marks.update(_received_tos(video))
            return bool(marks)

        await wait_until(marked, timeout=10)
    finally:
        await stream.stop()
        video.close()
    assert marks == {VIDEO_DSCP << 2}

    velocity = _tos_receiver()
    transport, _ = await asyncio.get_running_loop().create_datagram_endpoint(
        asyncio.DatagramProtocol, remote_addr=velocity.getsockname()
    )
    velocity_marks: set[int] = set()
    try:
        _expedite(transport)
        transport.sendto(b"$PVEL")

        def arrived() -> bool:
            velocity_marks.update(_received_tos(velocity))
            return bool(velocity_marks)

        await wait_until(arrived, timeout=5)
    finally:
        transport.close()
        velocity.close()
    assert velocity_marks == {VELOCITY_TOS}
    assert VELOCITY_TOS > VIDEO_DSCP << 2  # EF above AF41
