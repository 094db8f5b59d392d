"""Benchmark of the simulated vehicles: telemetry rates seen through MAVSDK and the simulator's CPU use.

    python bench/bench_sim_vehicle.py [--drones 3] [--seconds 20] [--base-port 34540] [--no-fly]

Starts ``skycap sim --drones N`` as its own process (as in a demo), connects one MAVSDK 4 instance per
vehicle (``udpin://0.0.0.0:<base+i>``, as the onboard agents do), arms and takes off every vehicle
(so the controllers and dynamics do real work), then subscribes to the telemetry a flight recorder uses
and counts callbacks for ``--seconds``. Prints per-vehicle rates (Hz) and the simulator process CPU
(% of one core, from /proc), plus this process's CPU (MAVSDK + Python subscribers) for reference.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import describe_machine  # noqa: E402

STREAMS = (
    "position_velocity_ned",
    "attitude_quaternion",
    "attitude_euler",
    "position",
    "raw_gps",
    "battery",
    "health",
    "landed_state",
)


def _machine() -> str:
    return describe_machine()

def _cpu_s(pid: int) -> float:
    """user + system CPU seconds of a process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def _vehicle(i: int, port: int, seconds: float, fly: bool, counts: dict, started: asyncio.Event):
    from mavsdk.asyncio import Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
    from mavsdk.component_type import ComponentType

    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    await mavsdk.add_any_connection(f"udpin://0.0.0.0:{port}")
    system = await mavsdk.first_autopilot(20.0)
    if system is None:
        raise SystemExit(f"vehicle {i}: no autopilot on udp {port}")
    tel, act = TelemetryAsync(system), ActionAsync(system)
    while True:
        h = await tel.health()
        if h.is_global_position_ok and h.is_home_position_ok and h.is_armable:
            break
        await asyncio.sleep(0.2)
    if fly:
        await act.arm()
        await act.takeoff()
    c = counts[i] = {s: 0 for s in STREAMS}

    async def count(name):
        async for _ in getattr(tel, f"subscribe_{name}")():
            if started.is_set():
                c[name] += 1

    tasks = [asyncio.ensure_future(count(s)) for s in STREAMS]
    await asyncio.sleep(seconds + 6.0)
    for t in tasks:
        t.cancel()
    return mavsdk


async def _main(args) -> None:
    ports = [args.base_port + i for i in range(args.drones)]
    cmd = [
        sys.executable,
        "-m",
        "apps.cli",
        "--log-level",
        "WARNING",
        "sim",
        "--drones",
        str(args.drones),
        "--set",
        f"ports.offboard_base={args.base_port}",
        "--set",
        "ports.local_base=0",
        "--set",
        "ports.gcs_port=0",
    ]
    sim = subprocess.Popen(cmd)
    counts: dict = {}
    started = asyncio.Event()
    try:
        tasks = [
            asyncio.ensure_future(_vehicle(i, p, args.seconds, not args.no_fly, counts, started))
            for i, p in enumerate(ports)
        ]
        await asyncio.sleep(5.0)  # connect, health, take off
        sim_cpu0, own_cpu0, t0 = _cpu_s(sim.pid), _cpu_s(os.getpid()), time.monotonic()
        started.set()
        await asyncio.sleep(args.seconds)
        started.clear()
        dt = time.monotonic() - t0
        sim_cpu, own_cpu = (_cpu_s(sim.pid) - sim_cpu0) / dt, (_cpu_s(os.getpid()) - own_cpu0) / dt
        mavsdks = await asyncio.gather(*tasks)
        for m in mavsdks:
            m.destroy()
    finally:
        sim.terminate()
        sim.wait(10)

    print(f"\nMachine: {_machine()}")
    print(
        f"{args.drones} simulated vehicles, {'flying (takeoff + hold)' if not args.no_fly else 'on the ground'}, "
        f"{dt:.1f} s measured; MAVSDK 4 telemetry callbacks per second:\n"
    )
    head = "| stream | " + " | ".join(f"vehicle {i + 1}" for i in range(args.drones)) + " |"
    print(head)
    print("|" + "---|" * (args.drones + 1))
    for s in STREAMS:
        print(f"| {s} | " + " | ".join(f"{counts.get(i, {}).get(s, 0) / dt:.1f}" for i in range(args.drones)) + " |")
    print("\n| process | CPU (% of one core) |\n|---|---|")
    print(f"| simulator (`skycap sim --drones {args.drones}`) | {100 * sim_cpu:.1f} |")
    print(f"| this process ({args.drones} MAVSDK instances + Python subscribers) | {100 * own_cpu:.1f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drones", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--base-port", type=int, default=34540)
    ap.add_argument("--no-fly", action="store_true", help="stay on the ground (no arm/takeoff)")
    asyncio.run(_main(ap.parse_args()))


if __name__ == "__main__":
    main()
