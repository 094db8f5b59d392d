"""The agent process (``skycap agent``): transport, recorder and autopilot opened, the agent run until a signal."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal

from comms.transport import Transport
from flightdata.folder import Sortie
from flightdata.recorder import Recorder
from onboard.agent.autopilot import MavsdkAutopilot
from onboard.agent.loop import Agent
from onboard.config import AgentConfig
from skycap.config import save_config
from skycap.sdnotify import Notifier

log = logging.getLogger(__name__)

__all__ = ["run_agent"]


async def run_agent(cfg: AgentConfig) -> int:
    """Process entry: open the transport and the recorder, run the agent until SIGTERM/SIGINT. Under systemd
    (``Type=notify``, deploy/skycap-agent.service) it reports its progress, is ready once the autopilot link and
    the recorder are up, and pings the watchdog from the control loop (:class:`skycap.sdnotify.Notifier`)."""
    cfg.validate()
    notifier = Notifier.from_env()
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    recorder = None
    if cfg.record.enabled:
        notifier.status(f"{cfg.drone_id}: opening the recording in {cfg.record.dir}")
        # each start is a new sortie: a new file, so a restart never touches the last recording
        recorder = Recorder.new_sortie(cfg.record.dir, cfg.drone_id,
                                       metadata={"fleet": cfg.fleet, "connection": cfg.connection})
        save_config(cfg, Sortie.of(recorder.path).config_path)
    notifier.status(f"{cfg.drone_id}: joining the fleet network")
    bus = Transport.open(cfg.transport, node_id=cfg.drone_id)
    camera = None
    if cfg.camera.source != "sim" and cfg.camera.in_agent:
        # the capture runs in this process (a thread) and publishes like a separate camera service would: the
        # agent's recorder and detector and the ground station all take the frames from the one capture
        from onboard.camera.service import CameraService

        camera = CameraService(cfg.camera, bus, cfg.fleet, cfg.drone_id)
        camera.start()
    origin = (cfg.origin.lat_deg, cfg.origin.lon_deg, cfg.origin.alt_m)
    agent = Agent(cfg, bus, MavsdkAutopilot(cfg.drone_id, origin=origin), recorder, notifier=notifier)
    try:
        await agent.run(stop)
    finally:
        if cfg.mode == "track" and recorder is not None:
            try:
                p = Sortie.of(recorder.path).track_stats_path  # this sortie's counters, beside its recording
                p.write_text(json.dumps(agent.tracking_stats()))
            except Exception as e:
                log.error("%s: writing the tracking statistics failed: %s", cfg.drone_id, e)
        if camera is not None:
            camera.stop()
        if recorder is not None:
            recorder.close()
        bus.close()
    log.info("%s: agent stopped (pid %d)", cfg.drone_id, os.getpid())
    return 0
