"""The onboard agent: one process per drone, on its companion computer.

:class:`Agent` (:mod:`onboard.agent.loop`) is a small loop wiring parts with one job each: the autopilot link
(:mod:`~onboard.agent.autopilot`, its :class:`~onboard.agent.telemetry.Telemetry` record), the mission state
machine (:mod:`onboard.mission`), the setpoint source (:mod:`onboard.setpoint`, :mod:`onboard.orbit`, or in track mode
:mod:`~onboard.agent.formation`), the tracking capture (:mod:`~onboard.agent.tracking`), the formation
failsafes (:mod:`~onboard.agent.failsafes`), publishing and recording (:mod:`~onboard.agent.outbox`).
:func:`run_agent` (:mod:`onboard.agent.process`) is the ``skycap agent`` process.
"""

from onboard.agent.loop import Agent
from onboard.agent.perception import PerceptionStage
from onboard.agent.process import run_agent
from onboard.agent.rates import RateMeter

__all__ = ["Agent", "PerceptionStage", "RateMeter", "run_agent"]
