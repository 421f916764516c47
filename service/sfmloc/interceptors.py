"""gRPC server interceptors shared by our two services (localization server and builder).

``MalformedRequestInterceptor`` (and ``SyncMalformedRequestInterceptor``): a request that is
not a valid protobuf message of the method's type ends with INVALID_ARGUMENT and a message
saying so. Without it grpc answers such bytes with UNKNOWN or INTERNAL (its deserializer raises
before any handler of ours runs), which tells a client nothing and looks like a server bug.

``ErrorStatusInterceptor`` (grpc.aio) and ``SyncErrorStatusInterceptor`` (grpc's thread-pool
server, the builder): an exception a handler raises ends the call with the status the one table
gives it (``sfmloc_client.errors.STATUS_TABLE``), so handlers raise our errors and never pick a
status code themselves.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from typing import Any

import grpc

from .errors import WireError, code_of, message_of

log = logging.getLogger(__name__)


def status_of(exc: BaseException) -> grpc.StatusCode:
    """The gRPC status the one table (``sfmloc_client.errors.STATUS_TABLE``) gives ``exc``."""
    return grpc.StatusCode[code_of(exc)]


class _Malformed:
    """What a request that failed to parse becomes (the handler then refuses it)."""

    __slots__ = ("reason",)

    def __init__(self, reason: str) -> None:
        self.reason = reason

    @property
    def message(self) -> str:
        return f"malformed request: not a valid message ({self.reason})"


def _safe(deserializer: Callable[[bytes], Any] | None) -> Callable[[bytes], Any] | None:
    if deserializer is None:
        return None

    def parse(data: bytes) -> Any:
        try:
            return deserializer(data)
        except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError and friends
            return _Malformed(f"{type(exc).__name__}: {exc}")

    return parse


async def _refuse(context: grpc.aio.ServicerContext, bad: _Malformed) -> None:
    await context.abort(grpc.StatusCode.INVALID_ARGUMENT, bad.message)


def _wrap(behavior: Callable[..., Any], streaming_requests: bool) -> Callable[..., Any]:
    """``behavior`` with malformed requests refused first, of the same kind (an async
    generator, a coroutine or a plain function, as grpc.aio runs each differently)."""

    def requests_of(request: Any, context: grpc.aio.ServicerContext) -> Any:
        return _checked_requests(request, context) if streaming_requests else request

    if inspect.isasyncgenfunction(behavior):

        async def gen(request: Any, context: grpc.aio.ServicerContext) -> AsyncIterator[Any]:
            if isinstance(request, _Malformed):
                await _refuse(context, request)
            async for item in behavior(requests_of(request, context), context):
                yield item

        return gen
    if inspect.iscoroutinefunction(behavior):

        async def coro(request: Any, context: grpc.aio.ServicerContext) -> Any:
            if isinstance(request, _Malformed):
                await _refuse(context, request)
            return await behavior(requests_of(request, context), context)

        return coro
    if streaming_requests:
        return behavior  # a synchronous streaming handler: left as it is (none of ours)

    def plain(request: Any, context: Any) -> Any:
        if isinstance(request, _Malformed):
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, request.message)
        return behavior(request, context)

    return plain


async def _checked_requests(
    requests: AsyncIterator[Any], context: grpc.aio.ServicerContext
) -> AsyncIterator[Any]:
    # Raised, not aborted here: the handler reading the stream ends it through its own error
    # path (one abort, INVALID_ARGUMENT by the status table); aborting under it made the
    # handler abort a second time and log a traceback per malformed message.
    async for request in requests:
        if isinstance(request, _Malformed):
            raise WireError(request.message)
        yield request


_KINDS = (
    ("unary_unary", grpc.unary_unary_rpc_method_handler, False),
    ("unary_stream", grpc.unary_stream_rpc_method_handler, False),
    ("stream_unary", grpc.stream_unary_rpc_method_handler, True),
    ("stream_stream", grpc.stream_stream_rpc_method_handler, True),
)


def same_kind(
    handler: grpc.RpcMethodHandler,
    wrap: Callable[[Callable[..., Any], bool], Callable[..., Any]],
    request_deserializer: Callable[[bytes], Any] | None = None,
) -> grpc.RpcMethodHandler:
    """A method handler of the same kind as ``handler`` (unary or streaming on each side) with
    the behaviour ``wrap(behavior, streaming_requests)`` and, when given, another deserializer."""
    des = request_deserializer or handler.request_deserializer
    for attr, make, streaming in _KINDS:
        behavior = getattr(handler, attr)
        if behavior is not None:
            return make(wrap(behavior, streaming), des, handler.response_serializer)
    return handler


class MalformedRequestInterceptor(grpc.aio.ServerInterceptor):
    """Unparsable request bytes: INVALID_ARGUMENT with a message, for every method."""

    async def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler]],
        handler_call_details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler:
        handler = await continuation(handler_call_details)
        if handler is None:
            return handler
        return same_kind(handler, _wrap, _safe(handler.request_deserializer))


class SyncMalformedRequestInterceptor(grpc.ServerInterceptor):
    """``MalformedRequestInterceptor`` for grpc's thread-pool server (the builder service)."""

    def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], grpc.RpcMethodHandler],
        handler_call_details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler:
        handler = continuation(handler_call_details)
        if handler is None:
            return handler
        return same_kind(handler, _wrap, _safe(handler.request_deserializer))


# ============================================================================ error status
def _log_failure(method: str, exc: BaseException) -> None:
    # The server's log formatters (server/logfmt.py) render ``event`` and ``fields``.
    fields = {"method": method.rsplit("/", 1)[-1], "code": code_of(exc), "error": message_of(exc)}
    log.info(
        "rpc_failed method=%s code=%s error=%r",
        fields["method"],
        fields["code"],
        fields["error"],
        extra={"event": "rpc_failed", "fields": fields},
    )


def _aio_error_wrap(method: str) -> Callable[[Callable[..., Any], bool], Callable[..., Any]]:
    async def end(context: grpc.aio.ServicerContext, exc: BaseException) -> None:
        _log_failure(method, exc)
        await context.abort(status_of(exc), message_of(exc))

    def wrap(behavior: Callable[..., Any], streaming_requests: bool) -> Callable[..., Any]:
        if inspect.isasyncgenfunction(behavior):

            async def gen(request: Any, context: grpc.aio.ServicerContext) -> AsyncIterator[Any]:
                try:
                    async for item in behavior(request, context):
                        yield item
                except (asyncio.CancelledError, grpc.aio.AbortError):
                    raise  # cancelled, or the handler chose its status itself
                except Exception as exc:  # noqa: BLE001 - every failure gets the table's status
                    await end(context, exc)

            return gen
        if inspect.iscoroutinefunction(behavior):

            async def coro(request: Any, context: grpc.aio.ServicerContext) -> Any:
                try:
                    return await behavior(request, context)
                except (asyncio.CancelledError, grpc.aio.AbortError):
                    raise
                except Exception as exc:  # noqa: BLE001
                    await end(context, exc)

            return coro
        return behavior  # grpc.aio runs none of our handlers synchronously

    return wrap


class ErrorStatusInterceptor(grpc.aio.ServerInterceptor):
    """A handler's exception ends its call with the table's status and our message."""

    async def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler]],
        handler_call_details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler:
        handler = await continuation(handler_call_details)
        if handler is None:
            return handler
        return same_kind(handler, _aio_error_wrap(handler_call_details.method))


def _aborted(context: grpc.ServicerContext, exc: BaseException) -> bool:
    # grpc's thread-pool server signals abort() with a bare Exception after setting the code.
    return type(exc) is Exception and context.code() is not None


def _sync_error_wrap(method: str) -> Callable[[Callable[..., Any], bool], Callable[..., Any]]:
    def end(context: grpc.ServicerContext, exc: Exception) -> None:
        if _aborted(context, exc):
            raise exc
        _log_failure(method, exc)
        context.abort(status_of(exc), message_of(exc))

    def wrap(behavior: Callable[..., Any], streaming_requests: bool) -> Callable[..., Any]:
        if inspect.isgeneratorfunction(behavior):

            def gen(request: Any, context: grpc.ServicerContext) -> Iterator[Any]:
                try:
                    yield from behavior(request, context)
                except Exception as exc:  # noqa: BLE001
                    end(context, exc)

            return gen

        def plain(request: Any, context: grpc.ServicerContext) -> Any:
            try:
                return behavior(request, context)
            except Exception as exc:  # noqa: BLE001
                end(context, exc)

        return plain

    return wrap


class SyncErrorStatusInterceptor(grpc.ServerInterceptor):
    """``ErrorStatusInterceptor`` for grpc's thread-pool server (the builder service)."""

    def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], grpc.RpcMethodHandler],
        handler_call_details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler:
        handler = continuation(handler_call_details)
        if handler is None:
            return handler
        return same_kind(handler, _sync_error_wrap(handler_call_details.method))
