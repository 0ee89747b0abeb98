"""Render streams: a client that renders a moving camera (the viewer while you drag) names its
requests ``stream`` + ``seq``, and a request that a newer one of its stream has made stale is
dropped instead of rendered.

A stream is any client-chosen token (the viewer makes a random one per page); ``seq`` numbers the
stream's requests and only grows. The registry keeps, per stream, the largest ``seq`` seen:

- a request whose ``seq`` is below it is stale on arrival: ``Superseded`` (409) at once;
- a request admitted with a larger ``seq`` marks every request of the stream with a smaller
  ``seq`` that is still waiting for a worker as superseded: the worker pool takes it out of its
  queue and it is answered 409 without being rendered (``WorkerPool.run(superseded=...)``).

A request that a worker has already taken runs to the end and answers 200 (a render cannot be
stopped half-way; its client ignores it). An equal ``seq`` is not stale (a retry after a 429 may
send it again). Everything runs on the event loop, so no lock is needed. At most ``max_streams``
streams are remembered (least recently used forgotten first: a forgotten stream only loses the
drop of its older requests, never a render).
"""
from __future__ import annotations

import asyncio
import contextlib
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable

from .errors import Superseded

__all__ = ["Streams", "Ticket"]


@dataclass(eq=False)
class Ticket:
    """One admitted request of a stream: ``superseded`` gets the newer ``seq`` as its result
    when a newer request of the stream arrives."""
    stream: str
    seq: int
    superseded: asyncio.Future


@dataclass(eq=False)
class _Stream:
    latest: int
    pending: set[Ticket] = field(default_factory=set)


class Streams:
    """The latest ``seq`` of each render stream (see the module docstring). ``on_reject
    ("superseded")`` is called for each request refused on arrival (metrics)."""

    def __init__(self, max_streams: int = 4096, *,
                 on_reject: Callable[[str], None] | None = None):
        if max_streams < 1:
            raise ValueError("max_streams >= 1 expected")
        self.max_streams = int(max_streams)
        self._on_reject = on_reject or (lambda reason: None)
        self._streams: OrderedDict[str, _Stream] = OrderedDict()

    def __len__(self) -> int:
        return len(self._streams)

    def latest(self, stream: str) -> int | None:
        s = self._streams.get(stream)
        return None if s is None else s.latest

    def admit(self, stream: str, seq: int) -> Ticket:
        """A ticket for request ``seq`` of ``stream``, or ``Superseded`` when the stream has seen a
        newer one. Marks the stream's waiting requests with a smaller ``seq`` as superseded."""
        s = self._streams.get(stream)
        if s is None:
            s = self._streams[stream] = _Stream(latest=seq)
            while len(self._streams) > self.max_streams:
                self._streams.popitem(last=False)
        else:
            self._streams.move_to_end(stream)
        if seq < s.latest:
            self._on_reject("superseded")
            raise Superseded(f"seq: {seq} of stream {stream!r} is older than its latest request "
                             f"(seq {s.latest}); nothing was rendered", newer=s.latest)
        if seq > s.latest:
            s.latest = seq
            for ticket in s.pending:
                if ticket.seq < seq and not ticket.superseded.done():
                    ticket.superseded.set_result(seq)
        ticket = Ticket(stream, seq, asyncio.get_running_loop().create_future())
        s.pending.add(ticket)
        return ticket

    def release(self, ticket: Ticket) -> None:
        """The request is answered (or running): forget its ticket."""
        s = self._streams.get(ticket.stream)
        if s is not None:
            s.pending.discard(ticket)
        if not ticket.superseded.done():
            ticket.superseded.cancel()

    @contextlib.contextmanager
    def ticket(self, stream: str | None, seq: int | None):
        """``admit`` for a request with a stream (yields its ticket), nothing without one
        (yields None); the ticket is released on leaving."""
        if stream is None or seq is None:
            yield None
            return
        ticket = self.admit(stream, seq)
        try:
            yield ticket
        finally:
            self.release(ticket)
