"""Roost's one layer over the Kubernetes API, shared by the operator, the agent and the CLI.

What lives here, each once: where every resource sits in the REST tree
(:mod:`.resources`, Roost's own kinds derived from :mod:`roost_api.resources`), the
Event manifest (:mod:`.events`), the patch rules — server-side apply skipped when
nothing changed, JSON merge patches that carry explicit nulls, ``resourceVersion``
preconditions — (:mod:`.patches`), one error hierarchy that tells temporary failures
from permanent ones (:mod:`.errors`), the REST client with per-caller timeouts
(:mod:`.client`) and kubeconfig loading as kubectl does it (:mod:`.kubeconfig`).

The layer imports neither kopf nor any Roost package but :mod:`roost_api`, and only
:mod:`.client` and :mod:`.kubeconfig` import the ``kubernetes`` client, so the agent pays
for it only in cluster mode. The mapping of :mod:`.errors` onto kopf's retry semantics
lives at the operator's handler edge (:mod:`roost_operator.edge`).
"""
