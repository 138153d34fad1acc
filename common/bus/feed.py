"""Event-feed subscriber that misses nothing (the ZeroMQ Guide's Clone pattern, ch. 5).

The broker publishes every event on a PUB socket as ``[type, stream, seq, event]`` and sends
``[HEARTBEAT, stream, last_seq, ""]`` when idle. PUB/SUB drops messages while a subscriber is
away or slow, so the subscriber keeps the last sequence number it delivered and fills any gap
from the broker's journal with SINCE requests:

1. subscribe to the feed first (live messages are buffered by ZeroMQ meanwhile);
2. ask SINCE ``last`` until caught up, delivering in order;
3. deliver live messages with ``seq == last + 1``; skip ``seq <= last`` (already delivered);
   on ``seq > last + 1`` or a heartbeat announcing ``last_seq > last``, go back to step 2;
4. if the feed is silent for ``liveness`` heartbeat intervals, reconnect and go to step 2.

A different ``stream`` id means the broker's journal was replaced: sequence numbers restart,
so the subscriber starts over from 0 of the new stream (and says so in the log).
"""

from __future__ import annotations

import collections
import logging
import time
from typing import Iterable, Iterator, Mapping

import zmq

from common.bus import protocol as P
from common.bus.client import BrokerClient, BrokerUnavailable
from common.bus.security import secure_client_socket
from common.config import broker_endpoint, feed_endpoint

log = logging.getLogger("tessera.feed")


class FeedSubscriber:
    """Ordered, gap-free event stream from the broker.

    Parameters
    ----------
    feed : str
        PUB endpoint of the broker, e.g. ``tcp://127.0.0.1:5556``.
    broker : str
        ROUTER endpoint (for SINCE requests).
    since : int or None
        Deliver every retained event with sequence number > ``since``; None = only new events.
    types : iterable of str, optional
        Deliver only these event types (the position still advances past the others).
    heartbeat_interval_s, liveness : float, int
        The broker's feed heartbeat; silence for ``interval * liveness`` means reconnect.

    Examples
    --------
    ::

        sub = FeedSubscriber.from_config(cfg, since=0)
        for seq, event in sub.events(timeout_s=5):
            print(seq, event["type"])
    """

    def __init__(self, feed: str, broker: str, *, since: int | None = None, types: Iterable[str] | None = None,
                 heartbeat_interval_s: float = 1.0, liveness: int = 3, context: zmq.Context | None = None,
                 security: Mapping | None = None):
        self.feed_endpoint = feed
        self.security = security or {}  # a config with [security]: CURVE keys when curve is on
        self.ctx = context or zmq.Context.instance()
        self.types = set(types) if types else None
        self.interval = float(heartbeat_interval_s)
        self.liveness = int(liveness)
        self.client = BrokerClient(broker, timeout_s=max(0.5, self.interval), retries=1, context=self.ctx,
                                   security=self.security)
        self.last: int | None = since
        self.stream: str | None = None
        self._ready: collections.deque = collections.deque()
        self._sub = None
        self._need_catchup = True
        self._heard = time.monotonic()
        self._connect()
        if since is None:  # "only new events" means new from now: fix the position at construction
            self._catch_up()

    @classmethod
    def from_config(cls, config: Mapping, **kw) -> "FeedSubscriber":
        b = config["broker"]
        return cls(feed_endpoint(config), broker_endpoint(config), heartbeat_interval_s=b["heartbeat_interval_s"],
                   liveness=b["heartbeat_liveness"], security=kw.pop("security", config), **kw)

    def close(self) -> None:
        if self._sub is not None:
            self._sub.close(linger=0)
            self._sub = None
        self.client.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _connect(self) -> None:
        if self._sub is not None:
            self._sub.close(linger=0)
        self._sub = secure_client_socket(self.ctx.socket(zmq.SUB), self.security)
        self._sub.setsockopt(zmq.LINGER, 0)
        self._sub.setsockopt(zmq.RCVHWM, 100000)
        self._sub.setsockopt(zmq.SUBSCRIBE, b"")
        self._sub.connect(self.feed_endpoint)
        self._need_catchup = True
        self._heard = time.monotonic()

    def _catch_up(self) -> bool:
        """Fill the gap from the journal; False if the broker did not answer (try again later)."""
        try:
            while True:
                after = self.last if self.last is not None else 1 << 62
                r = self.client.since(after, 1000, self.types)
                if self.stream is not None and r["stream"] != self.stream:
                    log.warning("feed stream changed %s -> %s (new broker journal): starting over at 0",
                                self.stream, r["stream"])
                    self.stream, self.last = r["stream"], 0
                    continue
                self.stream = r["stream"]
                if self.last is None:  # only new events: start at the broker's position
                    self.last = r["last_seq"]
                    break
                events = r["events"]
                if events and events[0][0] > self.last + 1:
                    log.warning("events %d..%d are no longer retained by the broker; continuing after them",
                                self.last + 1, events[0][0] - 1)
                for seq, body in events:
                    if seq > self.last:
                        self._deliver(seq, body)
                scanned = r.get("scanned_to")  # with a type filter: the broker looked this far
                if self.types is not None and isinstance(scanned, int) and scanned > self.last:
                    self.last = scanned
                if not events or self.last >= r["last_seq"]:
                    break
        except BrokerUnavailable:
            return False
        self._need_catchup = False
        return True

    def _deliver(self, seq: int, body: bytes) -> None:
        self.last = seq
        try:
            event = P.loads(body)
        except Exception:
            log.warning("undecodable event %d skipped", seq)
            return
        if not isinstance(event, dict):
            log.warning("event %d is not a map: skipped", seq)
            return
        if self.types is None or event.get("type") in self.types:
            self._ready.append((seq, event))

    def next(self, timeout_s: float = 1.0) -> tuple[int, dict] | None:
        """The next event as ``(seq, event)``, or None if none arrived within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self._ready:
                return self._ready.popleft()
            if self._need_catchup and self._catch_up() and self._ready:
                continue
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            if not self._sub.poll(min(left, self.interval) * 1000):
                if time.monotonic() - self._heard > self.interval * self.liveness:
                    log.info("feed silent for %.1f s: reconnecting", self.interval * self.liveness)
                    self._connect()
                continue
            frames = self._sub.recv_multipart()
            self._heard = time.monotonic()
            if len(frames) != 4:
                continue
            topic, stream, seq = frames[0], frames[1].decode(), int(frames[2])
            if stream != self.stream or self.last is None:
                self._need_catchup = True
                continue
            if topic == P.FEED_HEARTBEAT:
                if seq > self.last:
                    self._need_catchup = True
                continue
            if seq <= self.last:
                continue
            if seq == self.last + 1:
                self._deliver(seq, frames[3])
            else:
                self._need_catchup = True

    def events(self, timeout_s: float | None = None) -> Iterator[tuple[int, dict]]:
        """Iterate events; stops after ``timeout_s`` without any (None: never stops)."""
        while True:
            item = self.next(timeout_s if timeout_s is not None else 1.0)
            if item is None:
                if timeout_s is not None:
                    return
                continue
            yield item
