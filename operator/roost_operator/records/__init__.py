"""Every flight leaves a record: the operator's side (one bundle per finished Mission).

The agent on each vehicle records its flights and serves them over HTTP (``/records``,
reached through the API server's pod proxy of the agent pod). When a Mission that flew
ends, its reconciles gather the flights of its claimed vehicles that overlap the
Mission's run into one bundle on the operator's records volume. Split like the mission
controller — pure decisions, thin I/O:

``planning``
    Pure: which flights belong to a Mission, which files are still to fetch, what is
    missing and why, the bundle's and each vehicle's state, which bundles retention
    removes. Decision tables in ``tests/unit/test_operator_records_planning.py``.
``source``
    How the operator reaches a vehicle's records server (pod proxy, or a direct URL).
``bundle``
    The bundle directory: resumable downloads (HTTP Range) with sha256 checks, the
    manifest written atomically, retention.
``gather``
    One gathering round for one Mission: observe the agents, plan, fetch, write the
    manifest; returns the ``status.records`` the mission loop writes with the rest of
    the Mission's status (it stays the only writer of that status).
``server``
    Read-only HTTP over the bundles for ``roost records get`` and the dashboard.
"""
