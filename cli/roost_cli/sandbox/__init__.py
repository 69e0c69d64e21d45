"""A local fleet sandbox: a real control plane, simulated vehicles, the operator and agents.

``roost sandbox up`` (``make demo``) composes the pieces other packages provide: the
local control plane (``roost_localcluster``), fake vehicle nodes kept Ready by
kwok, one ``roost-agent`` process per vehicle, two ``roost-sim`` simulated autopilots per
vehicle (up to ten vehicles share one simulator process: :mod:`.sims`), and the
``roost-operator``. Nothing here re-implements those; it only starts
them, wires their ports together, records them (:mod:`.state`) and stops them again.
"""
