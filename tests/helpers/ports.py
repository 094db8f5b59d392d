"""Free loopback ports for tests (the implementation is the launchers' own: :mod:`skycap.ports`)."""

from skycap.ports import free_tcp_port, free_udp_base

__all__ = ["free_tcp_port", "free_udp_base"]
