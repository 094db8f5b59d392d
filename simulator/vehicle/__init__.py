"""Simulated PX4 multirotors speaking MAVLink like PX4 SITL (see ``README.md`` beside this file).

Pure models (no I/O): :mod:`.px4_modes`, :mod:`.dynamics`, :mod:`.controller`, :mod:`.environment`,
:mod:`.params`, :mod:`.autopilot` (:class:`~simulator.vehicle.autopilot.SimVehicle`); the UDP adapter is
:mod:`.mavlink_endpoint`; :class:`simulator.runner.SimWorld` runs N of them in real time.
"""
