"""``roost dashboard``: a live fleet view in the browser (see docs/dashboard.md).

:mod:`.model` builds the document the page shows from the cluster and the agents'
telemetry streams, :mod:`.sources` keeps it current (watches, WebSocket clients),
:mod:`.server` serves the page and pushes the document, :mod:`.actions_api` carries out
the guarded actions with :mod:`roost_cli.actions`.
"""
