"""The reconcile engine: what runs controllers, apart from what they decide.

``workqueue``
    A queue of names with a fixed pool of workers: a name is never reconciled twice at
    once, a failure is retried with backoff unless it is permanent.
``watches``
    Roost's own watches (list, then watch) into stores, and the fingerprints that tell a
    change that matters from a status tick.
``cache``
    Reads served from those stores, and writes that keep them current.
``errors``
    Whether a failure may pass by retrying (read from ``roost_kube.errors``, no kopf).
``leader``
    Leader election on a Lease: one replica acts, the others stand by.

kopf delivers the custom resources' events, runs the Missions' deletion behind their
finalizer and holds the settings. Both controllers run on this engine: a work queue
each (Vehicles, Missions) with the same coalescing, backoff, error split and deadlines,
fed by kopf's event handlers and by Roost's own watches, all of it only in the replica
holding the Lease. The Vehicle controller also reads through the watches' caches.
"""
