"""The reference answer of the link's test core (blockray.rtl.link.EchoCore), written from its
definition: b ^ ECHO_XOR, then b + 1, b + 2, ... (mod 256) per command byte b."""

from blockray.rtl.link import ECHO_XOR, EchoCore

__all__ = ["EchoCore", "echo"]


def echo(data, repeat=1):
    """EchoCore's answer to command bytes ``data``."""
    out = bytearray()
    for b in data:
        out.append(b ^ ECHO_XOR)
        out += bytes((b + k) & 0xFF for k in range(1, repeat))
    return bytes(out)
