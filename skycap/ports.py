"""Free loopback ports: for launchers that pick their own Zenoh and MAVLink endpoints (the fault suite,
``skycap gs --sim``) and for tests that open real sessions."""

from __future__ import annotations

import random
import socket


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free right now on ``host`` (for tests and launchers choosing endpoints)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def free_udp_base(n: int, lo: int = 30000, hi: int = 60000) -> int:
    """A base port with ``n`` consecutive UDP ports free right now (for launchers and tests: MAVLink base+i)."""
    for _ in range(200):
        base = random.randint(lo, hi - n)
        socks = []
        try:
            for i in range(n):
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                s.bind(("0.0.0.0", base + i))
                socks.append(s)
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError(f"no {n} consecutive free UDP ports in {lo}..{hi}")
