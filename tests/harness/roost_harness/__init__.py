"""Roost's test harness: a real Kubernetes control plane with kwok-simulated vehicle nodes.

See ``tests/harness/README.md``. The pieces: :mod:`~roost_harness.binaries` (build/locate the
upstream binaries), :mod:`~roost_harness.pki` (certificates), :mod:`~roost_harness.controlplane`
(start/stop), :mod:`~roost_harness.cluster` (client helpers for tests), :mod:`~roost_harness.nodes`
(fake vehicle nodes), :mod:`~roost_harness.clients` (kubectl and helm), :mod:`~roost_harness.cli`
(``roost-cluster``).
"""
