"""Helpers shared by the tests and the benchmarks (``bench/``), never shipped in the wheel.

Roost processes run against a :mod:`roost_localcluster` cluster (:mod:`.operator`,
:mod:`.agent`), node agents written as status writers (:mod:`.fakeagents`), the API writes a
process made (:mod:`.apiwrites`) and the chart's install arguments (:mod:`.chart`).
"""
