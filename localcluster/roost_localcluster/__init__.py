"""A real Kubernetes control plane on this machine, with kwok-simulated vehicle nodes.

The sandbox (``roost sandbox up``) and the test suite both need a cluster where no
container engine runs, so this is a product component, not test code. See
``localcluster/README.md``. The pieces: :mod:`~roost_localcluster.binaries` (build/locate
the upstream binaries), :mod:`~roost_localcluster.pki` (certificates),
:mod:`~roost_localcluster.controlplane` (start/stop), :mod:`~roost_localcluster.cluster`
(client helpers), :mod:`~roost_localcluster.nodes` (fake vehicle nodes),
:mod:`~roost_localcluster.clients` (kubectl and helm), :mod:`~roost_localcluster.cli`
(``roost-cluster``). Real nodes beside the kwok ones (kubelet, containerd, CNI, each in a
network namespace): :mod:`~roost_localcluster.realnode`, with
:mod:`~roost_localcluster.nodenet` (their network) and :mod:`~roost_localcluster.relay`
(their way to the API server).
"""
