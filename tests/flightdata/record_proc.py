"""Child process for the kill -9 test: records a drone's load until killed.

    python tests/flightdata/record_proc.py PATH FLUSH_INTERVAL_S

Per ~10 ms: one VehicleState (seq 1, 2, ...); every 10th: a 40 KB CameraFrame; every 100th: a Health.
Prints "recording" once the first second is on disk.
"""

from __future__ import annotations

import os
import sys
import time

from flightdata.recorder import Recorder
from shared_msgs import CameraFrame, Health, VehicleState


def main() -> None:
    path, flush_s = sys.argv[1], float(sys.argv[2])
    rec = Recorder(path, node_id="drone_1", flush_interval_s=flush_s)
    t0 = time.monotonic()
    announced = False
    i = 0
    while True:
        i += 1
        st = VehicleState(
            header=VehicleState.make_header("drone_1", seq=i),
            position_ned_m=(float(i), 0.0, -10.0),
            velocity_ned_m_s=(0.0, 0.0, 0.0),
            q_world_body=(1.0, 0.0, 0.0, 0.0),
        )
        rec.record_message("state", st)
        if i % 10 == 0:
            hdr = CameraFrame.make_header("drone_1", seq=i // 10)
            rec.record_message(
                "camera/image",
                CameraFrame(header=hdr, camera_id="cam0", frame_index=i // 10, encoding="jpeg",
                            width_px=640, height_px=480, data=os.urandom(40_000)),
            )
        if i % 100 == 0:
            rec.record_message("health", Health(header=Health.make_header("drone_1"), role="agent", state="orbit"))
        if not announced and time.monotonic() - t0 > 1.0 + 2 * flush_s:
            print("recording", flush=True)
            announced = True
        time.sleep(0.01)


if __name__ == "__main__":
    main()
