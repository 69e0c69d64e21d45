"""The ``roost`` command line: the fleet at a glance, and a local sandbox to try it in.

The CLI talks to the Kubernetes API directly (through :mod:`roost_kube`, which loads
kubeconfigs as kubectl does), never to the operator or the agents: everything it shows is
what the cluster records, so what ``roost status`` says is what ``kubectl`` would say. It
imports the API models and the shared command builder from ``roost_api``, the Kubernetes
layer, and nothing from the operator or the agent, so it runs on a laptop without kopf's
machinery.
"""
