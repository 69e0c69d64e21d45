"""Vehicle reconciliation: a Vehicle turns a node into a drone of the fleet.

See :mod:`roost_operator` for how the modules of this package divide the work.
"""
