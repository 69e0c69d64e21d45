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

kopf delivers the custom resources' events and holds the settings; the Vehicle
controller runs on this engine's queue, watches and caches; the Mission controller uses
its backoff and errors from one kopf daemon per Mission.
"""
