"""What the RTL reads from the ``platform`` its ``elaborate`` sees (synth/target.py builds them).

The RTL is target-neutral: ``platform=None`` or any object without these flags gives plain
Amaranth registers and ``*``. Kept here, below synth/, so that rtl/ never imports synth/.
"""

__all__ = ["product_platform"]


def product_platform(platform, unit):
    """The platform a unit's products see: ``platform``, or None (generic products) when
    ``unit`` is one of ``platform.fabric_units``."""
    return None if unit in getattr(platform, "fabric_units", ()) else platform
