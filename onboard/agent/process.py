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

    def open_recorder() -> Recorder:
        # each start is a new sortie: a new file, so a restart never touches the last recording
        rec = Recorder.new_sortie(cfg.record.dir, cfg.drone_id, flush_interval_s=cfg.record.flush_interval_s,
                                  metadata={"fleet": cfg.fleet, "connection": cfg.connection})
        save_config(cfg, Sortie.of(rec.path).config_path)
        return rec

    if cfg.record.enabled:
        notifier.status(f"{cfg.drone_id}: opening the recording in {cfg.record.dir}")
        recorder = open_recorder()
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
    if cfg.record.enabled:
        # a failed recorder (writer died, disk full) is reported in the health and replaced by a new recording
        agent.outbox.reopen_recorder = open_recorder
        agent.outbox.reopen_interval_s = cfg.record.reopen_interval_s
        agent.outbox.on_record_failure = agent.warnings.append
    if cfg.record.fault_signals:
        _recorder_fault_signals(loop, agent, cfg)
    try:
        await agent.run(stop)
    finally:
        # the one in use (a failed one was replaced), detached first: a message recorded while the camera and the
        # transport shut down must not find it closed, count a failure and open a new sortie
        recorder = agent.outbox.detach_recorder()
        if cfg.mode == "track" and recorder is not None:
            try:
                p = Sortie.of(recorder.path).track_stats_path  # this sortie's counters, beside its recording
                p.write_text(json.dumps(agent.tracking_stats()))
            except Exception as e:
                log.error("%s: writing the tracking statistics failed: %s", cfg.drone_id, e)
        if recorder is not None:
            try:  # the messages received and refused (and why), per subscription, beside the recording
                Sortie.of(recorder.path).transport_stats_path.write_text(json.dumps(bus.stats(), indent=1))
            except Exception as e:
                log.error("%s: writing the transport statistics failed: %s", cfg.drone_id, e)
        if camera is not None:
            camera.stop()
        if recorder is not None:
            try:
                recorder.close()
            except Exception as e:  # its writer failed (disk full): what it flushed stays readable
                log.error("%s: closing the recording: %s", cfg.drone_id, e)
        bus.close()
    log.info("%s: agent stopped (pid %d)", cfg.drone_id, os.getpid())
    return 0


def _recorder_fault_signals(loop: asyncio.AbstractEventLoop, agent: Agent, cfg: AgentConfig) -> None:
    """Fault injection (``record.fault_signals``): SIGUSR1 kills the recorder's writer thread, SIGUSR2 fills the
    recording folder's disk (simulated)."""
    from flightdata.recorder import simulate_disk_full

    def kill_writer() -> None:
        rec = agent.outbox.recorder
        log.warning("%s: FAULT (SIGUSR1): killing the recorder's writer thread (%s)", cfg.drone_id,
                    rec.path if rec is not None else "no recorder")
        if rec is not None:
            rec.inject_writer_failure("recorder writer killed (fault injection, SIGUSR1)")

    def disk_full() -> None:
        log.warning("%s: FAULT (SIGUSR2): the disk of %s is full from now on (simulated)", cfg.drone_id, cfg.record.dir)
        simulate_disk_full(cfg.record.dir)

    loop.add_signal_handler(signal.SIGUSR1, kill_writer)
    loop.add_signal_handler(signal.SIGUSR2, disk_full)
