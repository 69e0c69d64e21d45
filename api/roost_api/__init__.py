"""Roost's API: typed models of the roost.dev/v1alpha1 custom resources.

The models are the single source of truth: ``crds/`` is generated from them, the
operator computes desired state from them, and the node agent reads its configuration
and writes its status through them. This package imports neither kopf nor the agent, so
both sides can depend on it.
"""
