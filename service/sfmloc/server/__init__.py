"""The localization server: Zenoh and gRPC front-ends over a pool of engine workers.

One responsibility per module::

    config       ServerConfig (flags < environment SFMLOC_... < file < defaults)
    status       the one table: exception -> gRPC status code (also the Zenoh error codes)
    logfmt       structured log lines (key=value or JSON), set up by entry points only
    metrics      Prometheus text metrics and their HTTP endpoint
    protocol     the messages between the server and its engine workers (typed, msgpack)
    worker       the engine worker program: holds the maps and the Localizers of its sessions
    pool         the worker pool: starts, feeds and restarts the workers (processes or threads)
    maps         the map registry: load / replace / unload bundles on every worker
    sessions     per-client sessions, latest-frame-only intake, idle expiry
    zenoh_io     Zenoh: frames in, poses out, liveliness token, info queryable, builder maps
    grpc_service the gRPC Localization service, health and reflection
    facade       ``Localization``: all the front ends may ask (frames, images, maps, sessions)
    app          wiring, start-up, graceful shutdown (test servers: ``sfmloc.testing``)

Nothing here is imported by the engine; only this package talks Zenoh and gRPC.
"""
