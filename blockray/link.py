"""The serial link's constants (the framing itself is :mod:`blockray.framing`, the gateware
:mod:`blockray.rtl.link` and :mod:`blockray.rtl.framing`, the host's transport
:mod:`blockray.host_driver.board.serial_link`)."""

__all__ = ["DEFAULT_BAUD"]

#: the link's baud rate unless a bitstream is built for another (``--baud``): 3 Mbaud, the FT231X's fastest
DEFAULT_BAUD = 3_000_000
