"""The map builder service (``sfmloc builder serve``): builds bundles in worker processes,
streams their progress over gRPC (``MapBuilder``) and announces finished bundles on Zenoh.

``jobs`` is the transport-free core (queue, worker processes, progress, cancellation);
``grpc_service`` and ``announce`` are the transport; ``app`` wires them together."""
