"""gRPC server reflection for our two services, under both of its names.

grpcio-reflection (1.85) registers only ``grpc.reflection.v1alpha.ServerReflection``; clients
that speak the stable ``grpc.reflection.v1`` (recent grpcurl, Postman, grpcui, Kreya) try v1
first. The two protocols are the same messages under another package name (gRPC copied
v1alpha's reflection.proto to v1 unchanged; the field numbers are identical), so the v1 method
is the same servicer's stream handler, registered under the v1 service name.
"""

from __future__ import annotations

from collections.abc import Sequence

import grpc
from grpc_reflection.v1alpha import reflection, reflection_pb2

V1_SERVICE_NAME = "grpc.reflection.v1.ServerReflection"
V1ALPHA_SERVICE_NAME = reflection.SERVICE_NAME


def enable_reflection(service_names: Sequence[str], server: grpc.Server | grpc.aio.Server) -> None:
    """List ``service_names`` (and both reflection services) over v1alpha and v1 reflection."""
    names = (*service_names, V1ALPHA_SERVICE_NAME, V1_SERVICE_NAME)
    reflection.enable_server_reflection(names, server)
    if isinstance(server, grpc.aio.Server):
        servicer: reflection.ReflectionServicer = reflection.aio.ReflectionServicer(names)
    else:
        servicer = reflection.ReflectionServicer(names)
    handler = grpc.method_handlers_generic_handler(
        V1_SERVICE_NAME,
        {
            "ServerReflectionInfo": grpc.stream_stream_rpc_method_handler(
                servicer.ServerReflectionInfo,
                request_deserializer=reflection_pb2.ServerReflectionRequest.FromString,
                response_serializer=reflection_pb2.ServerReflectionResponse.SerializeToString,
            )
        },
    )
    server.add_generic_rpc_handlers((handler,))
