"""The Foxglove WebSocket subprotocol's two names, at the station's door (sans-IO).

``foxglove-sdk``'s server accepts only ``foxglove.sdk.v1``: the name is a constant in its Rust
handshake (``rust/foxglove/src/websocket/handshake.rs``: a request that does not offer it is
answered 400), with no setting to add another. Clients built on ``@foxglove/ws-protocol``'s
``FoxgloveClient`` (0.8 and before) and Lichtblick before its ``foxglove.sdk.v1`` support offer
only ``foxglove.websocket.v1``: the same protocol (the specification in foxglove/ws-protocol;
the SDK's messages are the ones that client decodes) under its older name. The door
(:mod:`stationd.foxglove_guard`) already reads the upgrade request's head, so for such a
client it offers the SDK its own name and names the older one back in the ``101`` answer
(a WebSocket client accepts only a subprotocol it offered). ``Sec-WebSocket-Accept`` depends
on the key alone, so the handshake stays valid. A client offering both is passed untouched.
"""

from __future__ import annotations

SDK = "foxglove.sdk.v1"
LEGACY = "foxglove.websocket.v1"
_HEADER = "sec-websocket-protocol"


def _renamed(head: bytes, old: str, new: str) -> tuple[bytes, bool]:
    """``head`` with the token ``old`` of its Sec-WebSocket-Protocol header(s) renamed."""
    lines = head.decode("latin-1").split("\r\n")
    changed = False
    for index, line in enumerate(lines):
        name, sep, value = line.partition(":")
        if not sep or name.strip().lower() != _HEADER:
            continue
        tokens = [token.strip() for token in value.split(",")]
        if old in tokens:
            renamed = ", ".join(new if token == old else token for token in tokens)
            lines[index] = f"{name}: {renamed}"
            changed = True
    return "\r\n".join(lines).encode("latin-1"), changed


def offered(head: bytes) -> set[str]:
    """The subprotocols an upgrade request offers."""
    names: set[str] = set()
    for line in head.decode("latin-1").split("\r\n")[1:]:
        name, sep, value = line.partition(":")
        if sep and name.strip().lower() == _HEADER:
            names.update(token.strip() for token in value.split(","))
    return names


def offer_sdk(head: bytes) -> tuple[bytes, bool]:
    """The request head to pass to the SDK, and whether its answer must be renamed back
    (:func:`name_legacy`): a client offering ``foxglove.websocket.v1`` and not the SDK's name
    is made to offer the SDK's instead."""
    names = offered(head)
    if SDK in names or LEGACY not in names:
        return head, False
    return _renamed(head, LEGACY, SDK)


def name_legacy(answer_head: bytes) -> bytes:
    """The SDK's answer head naming ``foxglove.websocket.v1``, as its client offered."""
    return _renamed(answer_head, SDK, LEGACY)[0]
