"""The onboard agent: one process per drone, on its companion computer (see :mod:`onboard.agent.loop`)."""

from onboard.agent.loop import Agent, PerceptionStage, RateMeter, run_agent

__all__ = ["Agent", "PerceptionStage", "RateMeter", "run_agent"]
