"""Synchronous multi-drone path following: Roost's reference mission.

Each vehicle follows a timed trajectory (``trajectory``); when one arrives late at a
task it reports its delay to a central monitor (``monitor``), which forwards it to every
other vehicle; a vehicle at a task waits ``max(d) - d`` so that transit times between
tasks stay the planned ones (``sync``). The onboard program (``follower``) reaches its
vehicle through one small interface (``vehicle.Vehicle``), implemented over MAVLink with
pymavlink; a mavros implementation would replace only that class.
"""
