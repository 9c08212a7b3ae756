"""Decoded subscriptions of the shapeloc client: :class:`Stream`.

The Zenoh callback only queues raw payloads; the consumer decodes them (iterating or with
:meth:`Stream.get`). Returned by the ``watch_*`` methods of
:class:`clients.client.ShapelocClient`; re-exported by :mod:`clients.client`.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, Generic, TypeVar

import zenoh
from pydantic import BaseModel

from schemas.codec import decode
from service.errors import InvalidMessage

M = TypeVar("M", bound=BaseModel)


def encoding_of(sample: Any) -> str | None:
    enc = getattr(sample, "encoding", None)
    return None if enc is None else str(enc)


class Stream(Generic[M]):
    """Decoded samples of a subscription, as an iterator (blocking) or via :meth:`get`.

    The Zenoh callback only queues raw payloads; decoding happens in the consumer. Undecodable
    samples are counted in :attr:`rejected` and skipped; messages failing ``accept`` are
    dropped. Close it (or use ``with``) to undeclare the subscriber.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        model: type[M],
        accept: Callable[[M], bool] | None = None,
        key_filter: Callable[[str], bool] | None = None,
    ) -> None:
        self._model = model
        self._accept = accept
        self._key_filter = key_filter
        self._queue: queue.Queue[tuple[str, bytes, str | None]] = queue.Queue()
        self.rejected = 0
        self._closed = threading.Event()
        self._sub = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        if self._key_filter is None or self._key_filter(key):
            self._queue.put((key, sample.payload.to_bytes(), encoding_of(sample)))

    def _decode(self, item: tuple[str, bytes, str | None]) -> tuple[str, M] | None:
        key, payload, enc = item
        try:
            msg = decode(self._model, payload, enc)
        except InvalidMessage:
            self.rejected += 1
            return None
        if self._accept is not None and not self._accept(msg):
            return None
        return key, msg

    def get(self, timeout: float | None = None) -> tuple[str, M] | None:
        """Next ``(key, message)``; ``None`` if nothing valid arrives within ``timeout`` s
        (``None``: wait until closed)."""
        end = None if timeout is None else time.monotonic() + timeout
        while not self._closed.is_set():
            wait = 0.2 if end is None else min(0.2, max(0.0, end - time.monotonic()))
            try:
                item = self._queue.get(timeout=wait)
            except queue.Empty:
                if end is not None and time.monotonic() >= end:
                    return None
                continue
            got = self._decode(item)
            if got is not None:
                return got
        return None

    def drain(self) -> list[tuple[str, M]]:
        """Everything already received, without waiting."""
        out = []
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return out
            got = self._decode(item)
            if got is not None:
                out.append(got)

    def __iter__(self) -> Iterator[tuple[str, M]]:
        while True:
            item = self.get(timeout=None)
            if item is None:
                return
            yield item

    def close(self) -> None:
        """Undeclare the subscriber (idempotent)."""
        if not self._closed.is_set():
            self._closed.set()
            with contextlib.suppress(zenoh.ZError):
                self._sub.undeclare()

    def __enter__(self) -> Stream[M]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
