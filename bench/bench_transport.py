"""Benchmark: Zenoh transport latency/throughput between two processes, and flight-recorder CPU.

    python bench/bench_transport.py                 # all (about 40 s)
    python bench/bench_transport.py --quick         # shorter runs

Latency and throughput are measured twice: plaintext ``tcp/`` and the fleet's secure transport (``tls/``, mutual
TLS with certificates from a fresh fleet CA and the fleet's Zenoh access control), with the CPU time both
processes spent during the latency run.

1. Latency: process A publishes VehicleState at 100 Hz and 40 KB CameraFrames at 10 Hz to process B
   (explicit tcp/127.0.0.1 endpoints, multicast scouting off, the default peer topology); B measures
   ``t_received_ns - header.t_sent_ns`` (same clock) including decode.
2. Throughput: A publishes as fast as it can (VehicleState, then 40 KB frames); B counts what it decodes.
4. Crash loss: a recorder process under the per-drone load is killed with SIGKILL; the data lost is the kill
   time minus the last log time found in the (non-finalised) file.
3. Recorder: the per-drone load (10 Hz 40 KB JPEG-like frames, 50 Hz state, 10 Hz detections, 1 Hz health
   and camera info) recorded for a while; CPU of the whole process minus the same load generator without
   a recorder, per compression.

Prints tables with the machine noted.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import describe_machine  # noqa: E402

from flightdata.recorder import Recorder  # noqa: E402
from comms.transport import Transport, TransportConfig  # noqa: E402
from tests.helpers.ports import free_tcp_port
from shared_msgs import (  # noqa: E402

    BoundingBox,
    CameraFrame,
    CameraInfo,
    Detections,
    Health,
    VehicleState,
    encode,
    keys,
)

FLEET = "bench"
CTL_KEY = keys.drone_key(FLEET, "drone_1", "bench/ctl")
SUB_ALIVE_KEY = keys.drone_key(FLEET, "drone_1", "bench/sub_alive")
EYE4 = tuple(float(x) for x in np.eye(4).reshape(-1))


def machine() -> str:
    return describe_machine()

def state(i: int) -> VehicleState:
    return VehicleState(
        header=VehicleState.make_header("drone_1"),
        position_ned_m=(float(i), 1.0, -10.0), velocity_ned_m_s=(1.0, 0.0, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0),
        armed=True, flight_mode="OFFBOARD", landed_state="in_air",
    )


def frame(i: int, rng: np.random.Generator, size: int = 40_000) -> CameraFrame:
    return CameraFrame(
        header=CameraFrame.make_header("drone_1"), camera_id="cam0", frame_index=i, encoding="jpeg",
        width_px=1280, height_px=720, data=rng.bytes(size), T_world_cam=EYE4,
    )


def detections(i: int) -> Detections:
    box = BoundingBox(x_min_px=100, y_min_px=50, x_max_px=160, y_max_px=240, score=0.9)
    return Detections(
        header=Detections.make_header("drone_1"), camera_id="cam0", frame_index=i, detector="bench", mode="roi",
        boxes=[box], width_px=1280, height_px=720, T_world_cam=EYE4,
    )


# ------------------------------------------------------------------------------------------ subscriber
def run_subscriber(endpoint: str, keys_dir: str = "") -> None:
    """Child: subscribe to state + image; on a Health 'report' print JSON of latencies, counts and CPU seconds.

    Both ends present drone_1's certificate when secure (the path of camera images: camera service -> agent on
    one drone; the fleet ACL sends full-rate images to no one else)."""
    cfg = TransportConfig.local_peer(endpoint, keys_dir)
    lat: dict[str, list[int]] = {"state": [], "camera/image": []}
    first_last: dict[str, list[int]] = {}
    nbytes: dict[str, int] = {"state": 0, "camera/image": 0}
    lock = threading.Lock()
    done = threading.Event()
    cpu0 = [time.process_time()]

    def on_msg(rx) -> None:
        topic = keys.parse_key(rx.key)[2]
        with lock:
            lat[topic].append(rx.t_received_ns - rx.msg.header.t_sent_ns)
            nbytes[topic] += len(rx.data)
            fl = first_last.setdefault(topic, [rx.t_received_ns, rx.t_received_ns])
            fl[1] = rx.t_received_ns

    with Transport.open(cfg, "bench_sub", identity="drone_1") as bus:
        subs = [
            bus.subscribe(keys.drone_key(FLEET, "drone_1", keys.STATE), on_msg, VehicleState),
            bus.subscribe(keys.drone_key(FLEET, "drone_1", keys.CAMERA_IMAGE), on_msg, CameraFrame),
        ]

        def on_ctl(rx) -> None:
            with lock:
                if rx.msg.state == "reset":
                    cpu0[0] = time.process_time()
                    for v in lat.values():
                        v.clear()
                    first_last.clear()
                    for k in nbytes:
                        nbytes[k] = 0
                    return
                print(json.dumps({"lat": lat, "first_last": first_last, "bytes": nbytes,
                                  "cpu_s": time.process_time() - cpu0[0],
                                  "malformed": sum(s.stats.malformed for s in subs)}), flush=True)
                if rx.msg.state == "quit":
                    done.set()

        bus.subscribe(CTL_KEY, on_ctl, Health)
        bus.declare_alive(SUB_ALIVE_KEY)
        done.wait(600)
        time.sleep(0.2)


# ------------------------------------------------------------------------------------------ publisher
class Bench:
    def __init__(self, keys_dir: str = "") -> None:
        self.endpoint = f"{'tls' if keys_dir else 'tcp'}/127.0.0.1:{free_tcp_port()}"
        self.bus = Transport.open(TransportConfig.rendezvous(self.endpoint, keys_dir), "bench", identity="drone_1")
        self.joined = threading.Event()
        self.bus.watch_presence(SUB_ALIVE_KEY, on_join=lambda k: self.joined.set())
        self.child = subprocess.Popen(
            [sys.executable, __file__, "--role", "sub", "--endpoint", self.endpoint, "--keys", keys_dir],
            stdout=subprocess.PIPE, text=True,
        )
        if not self.joined.wait(30):
            raise RuntimeError("subscriber process did not join")
        time.sleep(0.5)
        self.k_state = keys.drone_key(FLEET, "drone_1", keys.STATE)
        self.k_img = keys.drone_key(FLEET, "drone_1", keys.CAMERA_IMAGE)
        self.k_ctl = CTL_KEY

    def control(self, what: str) -> dict | None:
        self.bus.publish(self.k_ctl, Health(header=Health.make_header("drone_1"), role="tool", state=what))
        if what == "reset":
            time.sleep(0.2)
            return None
        return json.loads(self.child.stdout.readline())

    def close(self) -> None:
        self.control("quit")
        self.child.wait(30)
        self.bus.close()


def pct(v: list[int], q: float) -> float:
    return float(np.percentile(np.asarray(v) / 1e6, q)) if v else float("nan")


def bench_latency(b: Bench, seconds: float, label: str) -> list[list[str]]:
    rng = np.random.default_rng(0)
    b.control("reset")
    cpu0 = time.process_time()
    n = int(seconds * 100)
    t_next = time.perf_counter()
    sent = {"state": 0, "camera/image": 0}
    for i in range(n):
        b.bus.publish(b.k_state, state(i))
        sent["state"] += 1
        if i % 10 == 0:
            b.bus.publish(b.k_img, frame(i, rng))
            sent["camera/image"] += 1
        t_next += 0.01
        time.sleep(max(0.0, t_next - time.perf_counter()))
    time.sleep(0.5)
    cpu_pub = time.process_time() - cpu0
    r = b.control("report")
    rows = []
    for topic, size in (("state", "~0.6 KB"), ("camera/image", "40 KB")):
        v = r["lat"][topic]
        rows.append([label, f"{topic} ({size}) at {100 if topic == 'state' else 10} Hz", f"{len(v)}/{sent[topic]}",
                     f"{pct(v, 50):.2f}", f"{pct(v, 95):.2f}", f"{pct(v, 99):.2f}", f"{max(v) / 1e6:.2f}",
                     f"{100 * cpu_pub / (seconds + 0.5):.2f} / {100 * r['cpu_s'] / (seconds + 0.5):.2f}"])
    return rows


def bench_throughput(b: Bench, n_state: int, n_img: int, label: str) -> list[list[str]]:
    rng = np.random.default_rng(1)
    rows = []
    frames = [frame(i, rng) for i in range(16)]
    for topic, n in (("state", n_state), ("camera/image", n_img)):
        b.control("reset")
        t0 = time.perf_counter()
        t0_wall_ns = time.time_ns()
        for i in range(n):
            if topic == "state":
                b.bus.publish(b.k_state, state(i))
            else:
                b.bus.publish(b.k_img, frames[i % 16])
        t_pub = time.perf_counter() - t0
        time.sleep(1.0)
        r = b.control("report")
        got = len(r["lat"][topic])
        fl = r["first_last"].get(topic, [t0_wall_ns, t0_wall_ns + 1])
        dt_rx = max((fl[1] - t0_wall_ns) / 1e9, 1e-9)  # first publish -> last receive
        rows.append([label, topic, str(n), f"{n / t_pub:,.0f}", f"{got} ({100 * got / n:.1f} %)", f"{got / dt_rx:,.0f}",
                     f"{r['bytes'][topic] / dt_rx / 1e6:.1f}"])
    return rows


# ------------------------------------------------------------------------------------------- recorder
def load_generator(rec: Recorder | None, seconds: float, rng: np.random.Generator) -> float:
    """Feed the per-drone load for ``seconds`` (50 Hz ticks); returns process CPU seconds used."""
    jpegs = [rng.bytes(int(s)) for s in rng.uniform(20_000, 60_000, size=32)]
    info = CameraInfo(header=CameraInfo.make_header("drone_1"), camera_id="cam0", width_px=1280, height_px=720,
                      fx_px=900, fy_px=900, cx_px=640, cy_px=360)
    c0 = time.process_time()
    t_next = time.perf_counter()
    for i in range(int(seconds * 50)):
        msgs = [("state", state(i))]
        if i % 5 == 0:
            f = CameraFrame(header=CameraFrame.make_header("drone_1"), camera_id="cam0", frame_index=i // 5,
                            encoding="jpeg", width_px=1280, height_px=720, data=jpegs[(i // 5) % 32], T_world_cam=EYE4)
            msgs += [("camera/image", f), ("detections", detections(i // 5))]
        if i % 50 == 0:
            msgs += [("health", Health(header=Health.make_header("drone_1"), role="agent", state="orbit")),
                     ("camera_info", info)]
        for topic, m in msgs:
            data = encode(m)  # the agent gets these bytes back from Transport.publish
            if rec is not None:
                rec.record(topic, data)
        t_next += 0.02
        time.sleep(max(0.0, t_next - time.perf_counter()))
    if rec is not None:
        rec.close()
    return time.process_time() - c0


def bench_recorder(seconds: float) -> list[list[str]]:
    rows = []
    base = load_generator(None, seconds, np.random.default_rng(2))
    for comp in ("zstd", "lz4", "none"):
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "drone_1.s001.mcap"
            rec = Recorder(path, node_id="drone_1", compression=comp)
            cpu = load_generator(rec, seconds, np.random.default_rng(2))
            st = rec.stats()
            size = path.stat().st_size
        rows.append([comp, f"{st['written'] / seconds:.0f}", f"{st['bytes'] / seconds / 1e6:.2f}",
                     f"{size / seconds / 1e6:.2f}", f"{100 * (cpu - base) / seconds:.1f}", str(st["dropped"]),
                     str(st["flushes"])])
    rows.append(["(load generator alone)", "", "", "", f"{100 * base / seconds:.1f} (subtracted)", "", ""])
    return rows


def bench_kill(runs: int) -> list[list[str]]:
    import signal

    from flightdata.flightlog import FlightLog

    lost, counts = [], []
    rng = np.random.default_rng(4)
    for _ in range(runs):
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "drone_1.s001.mcap"
            child = subprocess.Popen([sys.executable, __file__, "--role", "rec", "--endpoint", str(path)],
                                     stdout=subprocess.PIPE, text=True)
            child.stdout.readline()
            time.sleep(2.0 + rng.uniform(0, 1.0))
            t_kill = time.time_ns()
            os.kill(child.pid, signal.SIGKILL)
            child.wait()
            msgs = list(FlightLog(path).messages(decode_messages=False))
            lost.append((t_kill - max(m.log_time_ns for m in msgs)) / 1e9)
            counts.append(len(msgs))
    return [[str(runs), f"{min(lost):.2f}", f"{float(np.median(lost)):.2f}", f"{max(lost):.2f}",
             f"{int(np.median(counts))}"]]


def table(title: str, header: list[str], rows: list[list[str]]) -> str:
    w = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    line = lambda cells: "| " + " | ".join(c.ljust(w[i]) for i, c in enumerate(cells)) + " |"  # noqa: E731
    return "\n".join([f"\n{title}", line(header), "|" + "|".join("-" * (x + 2) for x in w) + "|", *map(line, rows)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--role", default="bench", choices=["bench", "sub", "rec"])
    ap.add_argument("--endpoint", default="")
    ap.add_argument("--keys", default="", help="(child) fleet folder for the secure run")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    if args.role == "sub":
        run_subscriber(args.endpoint, args.keys)
        return
    if args.role == "rec":
        rec = Recorder(args.endpoint, node_id="drone_1")
        print("recording", flush=True)
        load_generator(rec, 3600.0, np.random.default_rng(3))
        return
    quick = args.quick
    import logging

    logging.basicConfig(level=logging.ERROR)  # the expected "not finalised" warnings of the kill runs
    print(f"machine: {machine()}")
    print(f"load average at start: {os.getloadavg()}")
    from comms.security import FleetKeys

    lat, thr = [], []
    with tempfile.TemporaryDirectory() as d:
        fleet_keys = FleetKeys.create(Path(d) / "fleet", FLEET, drones=["drone_1"])
        for label, keys_dir in (("tcp (plaintext)", ""), ("tls (mTLS + ACL)", str(fleet_keys.folder))):
            b = Bench(keys_dir)
            try:
                lat += bench_latency(b, 3.0 if quick else 10.0, label)
                thr += bench_throughput(b, 5_000 if quick else 20_000, 500 if quick else 2_000, label)
            finally:
                b.close()
    print(table("publish -> receive latency, two processes, Zenoh peers on 127.0.0.1 (ms, includes encode+decode); "
                "CPU % of one core during the run, publisher / subscriber process",
                ["transport", "stream", "received", "p50", "p95", "p99", "max", "CPU % pub / sub"], lat))
    print(table("throughput, publisher as fast as it can (congestion control DROP for these topics)",
                ["transport", "topic", "sent", "publish msg/s", "received", "end-to-end msg/s", "end-to-end MB/s"], thr))
    rec = bench_recorder(5.0 if quick else 15.0)
    print(table("flight recorder, per-drone load: 50 Hz state + 10 Hz 20-60 KB JPEG + 10 Hz detections + 1 Hz health/info",
                ["compression", "msg/s", "in MB/s", "file MB/s", "CPU % of one core", "dropped", "fsyncs"], rec))
    print(table("kill -9 of a recording process (default flush interval 0.5 s), data lost at the end",
                ["runs", "lost s: min", "median", "max", "messages read back (median)"], bench_kill(3 if quick else 8)))
    print(f"\nmax RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB; "
          f"load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
